"""`write_dataset`: a dataset folder from one's own arrays, ready for `gns train`.

    write_dataset("data/mine", {"train": [Trajectory(positions, types), ...], "valid": [...]},
                  dt=0.0025, bounds=[[0.0, 1.0], [0.0, 1.0]], connectivity_radius=0.015)

writes metadata.json (with the statistics of the train split) and one file per split in the
layout asked for. Every input is checked before it is written, with an error that names the
argument, or the split and trajectory, and the bad value; whatever passes reads back with
`open_dataset` and has no problems in `validate_dataset`. The folder is built under a temporary
name and renamed into place at the end (`gns.files`), so an error leaves nothing behind.
Splits may be lazy iterables: trajectories are checked and written one at a time.
"""

from __future__ import annotations

import math
import os
from collections.abc import Iterable, Iterator, Mapping, Sequence
from typing import Any

import numpy as np

from gns.data.convert import _SUFFIX, _writer, adapt
from gns.data.dataset import SPLITS
from gns.data.errors import DatasetError
from gns.data.metadata import _KNOWN, DEFAULT_KINEMATIC_TYPES, Metadata
from gns.data.stats import StatisticsAccumulator
from gns.data.trajectory import Trajectory
from gns.data.validate import DEFAULT_KNOWN_TYPES
from gns.files import atomic_folder

# LagrangeBench numbers its particle types differently (and validates them so); datasets
# written from one's own arrays use the DeepMind type table, so it is not offered here.
LAYOUTS = ("deepmind", "npz", "h5")

TrajectoryLike = Trajectory | Mapping[str, Any]


def write_dataset(
    path: str | os.PathLike[str],
    splits: Mapping[str, Iterable[TrajectoryLike]],
    *,
    dt: float,
    bounds: Sequence[Sequence[float]],
    connectivity_radius: float,
    layout: str = "deepmind",
    kinematic_particle_types: Iterable[int] = DEFAULT_KINEMATIC_TYPES,
    periodic: bool | Sequence[bool] = False,
    extra: Mapping[str, Any] | None = None,
) -> Metadata:
    """Write `splits` as a new dataset folder at `path` and return the metadata written.

    splits: "train" (required: the statistics come from it), "valid" and "test", each an
        iterable of gns.data.Trajectory or of mappings with "positions" (T, N, D),
        "particle_type" (N,) and optionally "step_context" (T, C) and "material_property"
        (scalar or (N,)). Every trajectory of every split has the same T frames.
    dt: seconds per frame. bounds: D pairs (lo, hi) of the domain; positions may lie up to
        `connectivity_radius` outside them (walls act from there), on periodic axes not at all.
    connectivity_radius: the radius of the model's graph (metadata default_connectivity_radius).
    layout: "deepmind" ({split}.tfrecord), "npz" (geoelements) or "h5" (ours).
    kinematic_particle_types: types that follow given positions (boundaries), default {3}.
    periodic: one flag for every axis, or one per axis.
    extra: further metadata.json keys, kept as given (plain JSON values).

    Raises ValueError (DatasetError for a bad trajectory) naming the bad value, and
    FileExistsError when `path` exists and is not an empty folder.
    """
    if layout not in LAYOUTS:
        raise ValueError(f"unknown layout {layout!r}; expected one of {', '.join(LAYOUTS)}")
    base = _base_metadata(dt, bounds, connectivity_radius, kinematic_particle_types, periodic)
    extras = dict(extra or {})
    clashing = sorted(set(extras) & set(_KNOWN))
    if clashing:
        raise ValueError(f"extra must not set the metadata keys gns writes itself: {clashing}")
    if not isinstance(splits, Mapping):
        raise ValueError(f"splits must map split names to trajectories, got {type(splits)}")
    unknown = [name for name in splits if name not in SPLITS]
    if unknown:
        raise ValueError(f"unknown split(s) {unknown}; expected names from {', '.join(SPLITS)}")
    if "train" not in splits:
        raise ValueError("splits needs a 'train' split: the statistics are computed from it")
    for name, trajectories in splits.items():
        if isinstance(trajectories, (Trajectory, Mapping, np.ndarray, str, bytes)):
            raise ValueError(
                f"splits[{name!r}] must be a list (or iterable) of trajectories, "
                f"got one {type(trajectories).__name__}"
            )

    checker = _Checker(base)
    accumulator = StatisticsAccumulator(base.kinematic_particle_types, base.period)
    has_material = False  # after `adapt`: npz keeps a constant step_context as a material
    # Train first: a check that fails there should not wait for the other splits to be written.
    order = sorted(splits, key=SPLITS.index)
    with atomic_folder(path) as tmp:
        for name in order:

            def stream(name: str = name) -> Iterator[Trajectory]:
                nonlocal has_material
                for index, item in enumerate(splits[name]):
                    checked = checker.check(item, name, index)
                    try:
                        trajectory = adapt(checked, layout)
                    except DatasetError as err:
                        raise DatasetError(f"splits[{name!r}]", err.problem, index) from None
                    has_material |= trajectory.material_property is not None
                    if name == "train":
                        accumulator.add(trajectory)
                    yield trajectory

            if _writer(layout)(tmp / f"{name}{_SUFFIX[layout]}", stream()) == 0:
                raise ValueError(f"splits[{name!r}] holds no trajectories")
        try:
            statistics = accumulator.result()
        except ValueError as err:
            raise ValueError(f"splits['train']: {err}") from err
        assert checker.frames is not None  # train was not empty
        metadata = statistics.apply_to(base.replace(sequence_length=checker.frames - 1))
        if has_material:
            metadata = metadata.replace(material_feature_len=1)
        metadata = metadata.replace(extra=extras)
        metadata.write_json(tmp / "metadata.json")
    return metadata.replace(source=os.path.join(os.fspath(path), "metadata.json"))


def _base_metadata(
    dt: float,
    bounds: Sequence[Sequence[float]],
    radius: float,
    kinematic: Iterable[int],
    periodic: bool | Sequence[bool],
) -> Metadata:
    """The metadata every split shares, from arguments checked here (sequence_length and the
    statistics are placeholders until the data has been seen)."""
    if not _positive(dt):
        raise ValueError(f"dt must be a positive number of seconds per frame, got {dt!r}")
    if not _positive(radius):
        raise ValueError(f"connectivity_radius must be a positive number, got {radius!r}")
    try:
        box = np.asarray(bounds, dtype=np.float64)
    except (TypeError, ValueError) as err:
        raise ValueError(f"bounds must be D pairs (lo, hi) of numbers, got {bounds!r}") from err
    if box.ndim != 2 or box.shape[1] != 2 or not 1 <= box.shape[0] <= 3:
        raise ValueError(f"bounds must be D pairs (lo, hi) with D in 1..3, got {bounds!r}")
    for axis, (lo, hi) in enumerate(box):
        if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
            raise ValueError(f"bounds[{axis}] = [{lo}, {hi}] is not an interval lo < hi")
    dim = box.shape[0]
    flags = (periodic,) * dim if isinstance(periodic, bool) else tuple(periodic)
    if len(flags) != dim or not all(isinstance(f, (bool, np.bool_)) for f in flags):
        raise ValueError(f"periodic must be a bool or {dim} bools (one per axis), got {periodic!r}")
    try:
        kinematic_types = frozenset(_integer(t) for t in kinematic)
    except (TypeError, ValueError) as err:
        raise ValueError(f"kinematic_particle_types must be integers, got {kinematic!r}") from err
    return Metadata(
        bounds=tuple((float(lo), float(hi)) for lo, hi in box),
        sequence_length=1,
        default_connectivity_radius=float(radius),
        dim=dim,
        dt=float(dt),
        kinematic_particle_types=kinematic_types,
        periodic_boundary_conditions=tuple(bool(f) for f in flags),
    )


def _positive(value: Any) -> bool:
    return bool(
        isinstance(value, (int, float, np.integer, np.floating))
        and not isinstance(value, bool)
        and math.isfinite(value)
        and value > 0
    )


def _integer(value: Any) -> int:
    if isinstance(value, bool) or int(value) != value:
        raise ValueError(value)
    return int(value)


class _Checker:
    """What validate_dataset would find, found before writing: the same frame count
    everywhere, the metadata's dimension, known and not only kinematic particle types,
    positions inside the bounds, and global features present in all trajectories or none."""

    def __init__(self, metadata: Metadata) -> None:
        self.metadata = metadata
        self.frames: int | None = None
        self.context: int | None = None  # step_context width; 0: none
        self.material: bool | None = None
        self.first = ""  # the trajectory that set the above, for messages

    def check(self, item: TrajectoryLike, split: str, index: int) -> Trajectory:
        where = f"splits[{split!r}]"
        trajectory = self._trajectory(item, where, index)

        def fail(problem: str) -> DatasetError:
            return DatasetError(where, problem, index)

        metadata = self.metadata
        if trajectory.dim != metadata.dim:
            raise fail(
                f"positions are {trajectory.dim}D (shape {trajectory.positions.shape}) but "
                f"bounds has {metadata.dim} axes"
            )
        context = 0 if trajectory.step_context is None else trajectory.step_context.shape[1]
        material = trajectory.material_property is not None
        if self.frames is None:
            self.frames, self.context, self.material = trajectory.num_frames, context, material
            self.first = f"{where}[{index}]"
        if trajectory.num_frames != self.frames:
            raise fail(
                f"{trajectory.num_frames} frames, but {self.first} has {self.frames}: every "
                "trajectory needs the same number (metadata holds one sequence_length)"
            )
        if trajectory.num_frames < 2:
            raise fail("a trajectory needs at least 2 frames")
        if context != self.context:
            raise fail(
                f"step_context has {context} features but {self.first} has {self.context} "
                "(0: none): every trajectory needs the same global features"
            )
        if material != self.material:
            raise fail(
                f"material_property is {'given' if material else 'missing'} but "
                f"{'missing' if material else 'given'} in {self.first}: give it for all or none"
            )

        types = trajectory.particle_type
        unknown = sorted(set(np.unique(types).tolist()) - DEFAULT_KNOWN_TYPES)
        if unknown:
            raise fail(
                f"particle_type holds {unknown}; types are 0..8 (the DeepMind table, "
                "3 = boundary, kinematic by default)"
            )
        if np.isin(types, list(metadata.kinematic_particle_types)).all():
            raise fail(
                f"every particle has a kinematic type {sorted(metadata.kinematic_particle_types)}:"
                " nothing would move by the model"
            )

        radius = metadata.default_connectivity_radius
        for axis, (lo, hi) in enumerate(metadata.bounds):
            slack = 0.0 if metadata.periodic_boundary_conditions[axis] else radius
            values = trajectory.positions[..., axis]
            outside = (values < lo - slack) | (values > hi + slack)
            if outside.any():
                frame, particle = np.argwhere(outside)[0]
                raise fail(
                    f"{int(outside.sum())} positions on axis {axis} outside bounds [{lo}, {hi}]"
                    f"{'' if slack == 0 else f' +- {slack}'}: the first is particle {particle} "
                    f"at frame {frame} ({values[frame, particle]:.6g})"
                )
        return trajectory

    @staticmethod
    def _trajectory(item: TrajectoryLike, where: str, index: int) -> Trajectory:
        if isinstance(item, Trajectory):
            return item
        if not isinstance(item, Mapping):
            raise DatasetError(
                where,
                "must be a gns.data.Trajectory or a mapping with 'positions' and "
                f"'particle_type', got {type(item).__name__}",
                index,
            )
        allowed = ("positions", "particle_type", "step_context", "material_property")
        unknown = sorted(set(item) - set(allowed))
        missing = [k for k in allowed[:2] if k not in item]
        if unknown or missing:
            raise DatasetError(
                where,
                f"keys {sorted(item)}: missing {missing}, unknown {unknown} (allowed: {allowed})",
                index,
            )
        # Trajectory checks shapes, dtypes and finiteness, naming this split and index.
        return Trajectory(
            item["positions"],
            item["particle_type"],
            item.get("step_context"),
            item.get("material_property"),
            key=index,
            source=where,
        )

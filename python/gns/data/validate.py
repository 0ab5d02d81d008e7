"""`validate_dataset`: check a dataset against its metadata and list every problem found.

Checks: metadata keys and shapes; every trajectory readable (framing, checksums, pickles, shapes,
finite values, consistent particle counts); frame count = sequence_length + 1 (with a hint when
it is off by one); particle types known to the layout; positions inside the bounds (within one
connectivity radius; exactly inside on periodic axes); step_context present exactly when
metadata has context statistics; and the statistics recomputed from the train split against the
stored ones, in per-frame units (with a hint when they look divided by dt).
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gns.data.dataset import available_splits, open_dataset
from gns.data.errors import DatasetError
from gns.data.metadata import STATISTICS_KEYS, Metadata
from gns.data.stats import StatisticsAccumulator
from gns.data.trajectory import Trajectory

# The paper's type table has 9 entries; LagrangeBench numbers its own types.
KNOWN_TYPES = {"lagrangebench": frozenset({-1, 0, 1, 2, 3})}
DEFAULT_KNOWN_TYPES = frozenset(range(9))


@dataclass(frozen=True)
class Problem:
    """One thing wrong with a dataset."""

    file: str
    message: str
    trajectory: int | None = None

    def __str__(self) -> str:
        where = (
            self.file if self.trajectory is None else f"{self.file}: trajectory {self.trajectory}"
        )
        return f"{where}: {self.message}"


def _check_trajectory(trajectory: Trajectory, metadata: Metadata, layout: str) -> Iterator[str]:
    expected = metadata.sequence_length + 1
    frames = trajectory.num_frames
    if frames != expected:
        hint = ""
        if frames == metadata.sequence_length:
            hint = " (off by one: sequence_length counts transitions, so records hold "
            hint += "sequence_length + 1 frames)"
        elif frames == expected + 1:
            hint = " (off by one: is sequence_length the frame count?)"
        yield f"{frames} frames, expected sequence_length + 1 = {expected}{hint}"

    known = KNOWN_TYPES.get(layout, DEFAULT_KNOWN_TYPES)
    unknown = sorted(set(np.unique(trajectory.particle_type).tolist()) - known)
    if unknown:
        yield f"unknown particle types {unknown} (known: {sorted(known)})"
    if np.isin(trajectory.particle_type, list(metadata.kinematic_particle_types)).all():
        yield "every particle is kinematic: nothing to learn"

    radius = metadata.default_connectivity_radius
    for axis, (lo, hi) in enumerate(metadata.bounds):
        values = trajectory.positions[..., axis]
        slack = 0.0 if metadata.periodic_boundary_conditions[axis] else radius
        outside = (values < lo - slack) | (values > hi + slack)
        if outside.any():
            frame = int(np.argwhere(outside)[0][0])
            yield (
                f"{int(outside.sum())} positions on axis {axis} outside bounds [{lo}, {hi}]"
                f"{'' if slack == 0 else f' +- {slack}'} (range {values.min():.6g} .. "
                f"{values.max():.6g}, first at frame {frame})"
            )

    wants_context = metadata.context_mean is not None
    if wants_context and trajectory.step_context is None:
        yield "metadata has context_mean but the trajectory has no step_context"
    if not wants_context and trajectory.step_context is not None and layout == "deepmind":
        yield "trajectory has step_context but metadata has no context_mean / context_std"
    if (
        wants_context
        and trajectory.step_context is not None
        and trajectory.step_context.shape[1] != len(metadata.context_mean or ())
    ):
        yield (
            f"step_context has {trajectory.step_context.shape[1]} features, metadata "
            f"context_mean has {len(metadata.context_mean or ())}"
        )


def _compare(
    name: str, stored: tuple[float, ...], computed: np.ndarray, scale: np.ndarray, dt: float
) -> str | None:
    """A message if `stored` differs from `computed` by more than 1% of `scale` per axis."""
    stored_arr = np.asarray(stored)
    tolerance = 0.01 * np.maximum(np.abs(scale), 1e-12)
    if np.all(np.abs(stored_arr - computed) <= tolerance):
        return None
    message = f"{name} = {list(stored)} but the train split gives {computed.tolist()}"
    power = 2 if name.startswith("acc") else 1
    physical = computed / dt**power
    if np.all(np.abs(stored_arr - physical) <= 0.01 * np.maximum(np.abs(physical), 1e-12)):
        message += f" (stored values look divided by dt^{power}: gns uses per-frame units)"
    return message


def validate_dataset(path: str | os.PathLike[str]) -> list[Problem]:
    """Every problem found in the dataset at `path` (empty if it is sound)."""
    problems: list[Problem] = []
    root = Path(path)
    splits = available_splits(root)
    if not splits:
        return [
            Problem(str(root), "no dataset here (no metadata.json or manifest.json, or no splits)")
        ]
    accumulator: StatisticsAccumulator | None = None
    metadata: Metadata | None = None
    for split in splits:
        try:
            dataset = open_dataset(root, split)
        except DatasetError as err:
            problems.append(Problem(err.path, err.problem, _as_int(err.trajectory)))
            continue
        metadata = dataset.metadata
        if split == "train":
            accumulator = StatisticsAccumulator(metadata.kinematic_particle_types, metadata.period)
        if len(dataset) == 0:
            problems.append(
                Problem(str(dataset.files[0] if dataset.files else root), f"{split} is empty")
            )
        for index in range(len(dataset)):
            try:
                trajectory = dataset[index]
            except DatasetError as err:
                problems.append(Problem(err.path, err.problem, _as_int(err.trajectory)))
                continue
            for message in _check_trajectory(trajectory, metadata, dataset.layout):
                problems.append(Problem(trajectory.source, message, index))
            if split == "train" and accumulator is not None:
                accumulator.add(trajectory)
    if metadata is not None:
        problems.extend(_check_statistics(root, metadata, accumulator))
    return problems


def _check_statistics(
    root: Path, metadata: Metadata, accumulator: StatisticsAccumulator | None
) -> list[Problem]:
    where = str(metadata.source)
    missing = [k for k in STATISTICS_KEYS if getattr(metadata, k) is None]
    out = []
    if missing:
        out.append(
            Problem(where, f"metadata lacks {', '.join(missing)} (run `gns stats {root} --write`)")
        )
    if accumulator is None:
        out.append(Problem(str(root), "no readable train split to check statistics against"))
        return out
    try:
        stats = accumulator.result()
    except ValueError as err:
        out.append(Problem(str(root), f"train split: {err}"))
        return out
    computed = {
        "vel_mean": (stats.vel_mean, stats.vel_std),
        "vel_std": (stats.vel_std, stats.vel_std),
        "acc_mean": (stats.acc_mean, stats.acc_std),
        "acc_std": (stats.acc_std, stats.acc_std),
    }
    for name, (value, scale) in computed.items():
        stored = getattr(metadata, name)
        if stored is not None:
            message = _compare(name, stored, value, scale, metadata.dt)
            if message:
                out.append(Problem(where, message))
    if stats.context_mean is not None and stats.context_std is not None:
        for name, value in (
            ("context_mean", stats.context_mean),
            ("context_std", stats.context_std),
        ):
            stored = getattr(metadata, name)
            if stored is not None and len(stored) == len(value):
                scale = np.maximum(stats.context_std, np.abs(stats.context_mean))
                message = _compare(name, stored, value, scale, 1.0)
                if message:
                    out.append(Problem(where, message.split(" (stored")[0]))
    return out


def _as_int(value: int | str | None) -> int | None:
    return value if isinstance(value, int) else None

"""`convert`: rewrite a dataset in another layout, atomically.

Targets: "deepmind" (metadata.json + {split}.tfrecord, checksummed), "npz" (geoelements variant A),
"h5" (ours: geoelements' h5 plus `step_context`) and "lagrangebench". The whole output folder is
built under a temporary name and renamed into place at the end, so a failure leaves nothing.

Global features move between the two ways layouts store them: DeepMind has only a per-frame
step_context, geoelements only a per-trajectory material_property. A constant one-feature
step_context becomes a scalar material_property and back; anything else that a target cannot
hold is an error, never silently dropped.

`frame_stride` k keeps every k-th frame (gns.data.at_frame_stride; dt becomes k dt): a coarser
time step makes each predicted acceleration k^2 times larger against the same input noise and a
rollout k times shorter. The train split keeps every phase (frames p, p + k, ... for p < k, each
its own trajectory, so no frame of the training data is lost); the other splits keep phase 0, so
a rollout still starts at the first frame. Every output trajectory has the same length, that of
phase k - 1, and the statistics are computed anew from the strided train split.

Several sources are written one after another into each split, e.g. data of a rare regime
added to a training set (a source named k times is written k times: its windows are then
drawn k times as often). They must describe the same scene (dimension, box, time step,
trajectory length, connectivity radius, kinematic types, periodicity), and the statistics are
computed anew from the whole train split written.
"""

from __future__ import annotations

import itertools
import os
from collections.abc import Callable, Iterable, Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from gns.data.dataset import available_splits, open_dataset
from gns.data.deepmind import write_tfrecord
from gns.data.errors import DatasetError
from gns.data.h5 import write_h5
from gns.data.metadata import STATISTICS_KEYS, Metadata, obstacles_json
from gns.data.npz import write_npz
from gns.data.stats import StatisticsAccumulator
from gns.data.stride import at_frame_stride, frames_at_stride
from gns.data.trajectory import Trajectory
from gns.files import atomic_folder

TARGETS = ("deepmind", "npz", "h5", "lagrangebench")
_SUFFIX = {"deepmind": ".tfrecord", "npz": ".npz", "h5": ".h5", "lagrangebench": ".h5"}


def _constant_scalar(context: np.ndarray) -> bool:
    return context.shape[1] == 1 and bool(np.all(context == context[0]))


def adapt(trajectory: Trajectory, to: str) -> Trajectory:
    """The trajectory with its global features stored the way layout `to` can hold them."""
    context, material = trajectory.step_context, trajectory.material_property

    def fail(problem: str) -> DatasetError:
        return DatasetError(trajectory.source, problem, trajectory.key)

    if to == "deepmind" and material is not None:
        if material.ndim != 0:
            raise fail("a per-particle material_property has no place in the DeepMind layout")
        if context is None:
            context = np.full((trajectory.num_frames, 1), material, dtype=np.float32)
        elif not (_constant_scalar(context) and context[0, 0] == material):
            raise fail("DeepMind layout cannot hold both step_context and material_property")
        material = None
    elif to == "npz" and context is not None:
        if not _constant_scalar(context):
            raise fail("the npz layout cannot hold a per-frame step_context; use deepmind or h5")
        if material is None:
            material = context[0, 0].reshape(())
        elif not (material.ndim == 0 and context[0, 0] == material):
            raise fail("npz layout cannot hold both step_context and material_property")
        context = None
    elif to == "lagrangebench" and (context is not None or material is not None):
        raise fail("LagrangeBench h5 cannot hold step_context or material_property")
    if context is trajectory.step_context and material is trajectory.material_property:
        return trajectory
    return Trajectory(
        trajectory.positions,
        trajectory.particle_type,
        context,
        material,
        key=trajectory.key,
        source=trajectory.source,
    )


def _writer(to: str) -> Callable[[Path, Iterable[Trajectory]], int]:
    if to == "deepmind":
        return write_tfrecord
    if to == "npz":
        return write_npz
    if to == "h5":
        return write_h5
    return lambda path, trajectories: write_h5(path, trajectories, layout="lagrangebench")


def convert(
    src: str | os.PathLike[str] | Sequence[str | os.PathLike[str]],
    dst: str | os.PathLike[str],
    to: str,
    *,
    splits: Iterable[str] | None = None,
    frame_stride: int = 1,
) -> dict[str, int]:
    """Write the dataset at `src` (or several, one after another) to the new folder `dst` in
    layout `to`.

    Returns the number of trajectories written per split. Missing statistics are computed from
    the train split while it is written (always, from several sources). `dst` must not exist or
    be an empty folder. `frame_stride` > 1 subsamples time as the module docstring says.
    Default `splits`: those every source has.
    """
    if to not in TARGETS:
        raise ValueError(f"unknown target layout {to!r}; expected one of {TARGETS}")
    if isinstance(frame_stride, bool) or not isinstance(frame_stride, int) or frame_stride < 1:
        raise ValueError(f"frame_stride must be a positive integer, got {frame_stride!r}")
    sources = [src] if isinstance(src, (str, os.PathLike)) else list(src)
    if not sources:
        raise ValueError("no source dataset to convert")
    others = [available_splits(source) for source in sources[1:]]
    chosen = (
        list(splits)
        if splits is not None
        else [s for s in available_splits(sources[0]) if all(s in o for o in others)]
    )
    if not chosen:
        raise DatasetError(sources[0], "no splits to convert (none that every source has)")
    metadata: Metadata | None = None
    counts: dict[str, int] = {}
    accumulator: StatisticsAccumulator | None = None
    has_context = has_material = False
    # A trajectory's key is its index in the written file, which the frame stride changes:
    # metadata.json's obstacles are keyed anew as the trajectories are written.
    obstacles: dict[str, dict[str, list[dict[str, Any]]]] = {}
    try:
        with atomic_folder(dst) as tmp:
            for split in chosen:
                datasets = [open_dataset(source, split) for source in sources]
                for other in datasets[1:]:
                    _check_same_scene(datasets[0].metadata, other.metadata)
                if metadata is None:
                    metadata = _strided_metadata(datasets[0].metadata, frame_stride)
                    if len(sources) > 1:  # the first source's statistics are not the whole's
                        metadata = _without_statistics(metadata)
                dataset = itertools.chain.from_iterable(datasets)
                if split == "train":
                    accumulator = StatisticsAccumulator(
                        metadata.kinematic_particle_types, metadata.period
                    )

                def stream(
                    dataset: Iterable[Trajectory] = dataset,
                    accumulator: StatisticsAccumulator | None = accumulator,
                    split: str = split,
                ) -> Iterator[Trajectory]:
                    nonlocal has_context, has_material
                    for index, trajectory in enumerate(_strided(dataset, split, frame_stride)):
                        if trajectory.obstacles is not None:
                            shapes = obstacles_json(trajectory.obstacles)
                            obstacles.setdefault(split, {})[str(index)] = shapes
                        adapted = adapt(trajectory, to)
                        has_context |= adapted.step_context is not None
                        has_material |= adapted.material_property is not None
                        if split == "train" and accumulator is not None:
                            accumulator.add(adapted)
                        yield adapted

                counts[split] = _writer(to)(tmp / f"{split}{_SUFFIX[to]}", stream())
            assert metadata is not None
            metadata = _target_metadata(metadata, accumulator, has_context, has_material)
            if metadata.has_obstacles:
                metadata = metadata.replace(extra={**metadata.extra, "obstacles": obstacles})
            metadata.write_json(tmp / "metadata.json")
    except FileExistsError as err:
        raise DatasetError(dst, str(err)) from err
    return counts


# What several sources written into one dataset must share.
_SCENE_FIELDS = (
    "dim",
    "bounds",
    "dt",
    "sequence_length",
    "default_connectivity_radius",
    "kinematic_particle_types",
    "periodic_boundary_conditions",
)


def _check_same_scene(first: Metadata, other: Metadata) -> None:
    for name in _SCENE_FIELDS:
        a, b = getattr(first, name), getattr(other, name)
        if a != b:
            raise DatasetError(
                other.source,
                f"its {name} is {b!r} but {first.source}'s is {a!r}: sources written into one "
                "dataset must describe the same scene",
            )


def _without_statistics(metadata: Metadata) -> Metadata:
    return metadata.replace(**dict.fromkeys((*STATISTICS_KEYS, "context_mean", "context_std")))


def _strided_metadata(metadata: Metadata, stride: int) -> Metadata:
    if stride == 1:
        return metadata
    frames = frames_at_stride(metadata.sequence_length + 1, stride)
    if frames < 2:
        raise ValueError(
            f"frame_stride {stride} leaves fewer than 2 frames of the "
            f"{metadata.sequence_length + 1} per trajectory"
        )
    # Per-frame statistics change with the time step: _target_metadata computes them anew.
    return metadata.replace(
        sequence_length=frames - 1, dt=metadata.dt * stride, **dict.fromkeys(STATISTICS_KEYS)
    )


def _strided(dataset: Iterable[Trajectory], split: str, stride: int) -> Iterable[Trajectory]:
    if stride == 1:
        return dataset
    return (
        at_frame_stride(trajectory, stride, phase=phase)
        for trajectory in dataset
        for phase in range(stride if split == "train" else 1)
    )


def _target_metadata(
    metadata: Metadata,
    accumulator: StatisticsAccumulator | None,
    has_context: bool,
    has_material: bool,
) -> Metadata:
    stats = accumulator.result() if accumulator is not None else None
    if not metadata.has_statistics:
        if stats is None:
            raise DatasetError(
                metadata.source, "metadata has no statistics and there is no train split"
            )
        metadata = metadata.replace(
            vel_mean=tuple(stats.vel_mean.tolist()),
            vel_std=tuple(stats.vel_std.tolist()),
            acc_mean=tuple(stats.acc_mean.tolist()),
            acc_std=tuple(stats.acc_std.tolist()),
        )
    if not has_context:
        metadata = metadata.replace(context_mean=None, context_std=None)
    elif metadata.context_mean is None and stats is not None and stats.context_mean is not None:
        assert stats.context_std is not None
        metadata = metadata.replace(
            context_mean=tuple(stats.context_mean.tolist()),
            context_std=tuple(stats.context_std.tolist()),
        )
    if has_material and not metadata.material_feature_len:
        metadata = metadata.replace(material_feature_len=1)
    return metadata

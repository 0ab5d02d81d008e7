"""Training-data augmentation: mirror images of windows.

A scene that is symmetric along an axis (the box, the walls' friction, gravity and every other
force unchanged by the reflection x_d -> lo_d + hi_d - x_d) gives a valid trajectory when mirrored
along it, so mirroring doubles the data a small dataset offers, for instance at the side walls
of a box of sand. The paper does not augment; it is off unless TrainConfig.mirror_axes names axes.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np

from gns.data.windows import Batch

__all__ = ["check_mirror_axes", "mirror_batch"]


def check_mirror_axes(
    axes: Sequence[int],
    dim: int,
    acceleration_mean: Sequence[float] | None,
    acceleration_std: Sequence[float] | None,
) -> None:
    """Refuses mirror axes a scene is visibly not symmetric along: an axis the scene lacks, and
    an axis along which the mean acceleration is larger than its std (gravity or another steady
    force points along it, and would be reversed). Obstacles, as kinematic particles or as
    shapes, are mirrored with everything else."""
    for axis in axes:
        if not 0 <= axis < dim:
            raise ValueError(f"mirror_axes contains {axis}; expected axes in 0..{dim - 1}")
        if acceleration_mean is None or acceleration_std is None:
            continue
        mean, std = abs(acceleration_mean[axis]), acceleration_std[axis]
        if mean > std:
            raise ValueError(
                f"mirror_axes contains {axis}, but the mean acceleration along it is {mean:.3g} "
                f"per step^2 against a std of {std:.3g}: a steady force (gravity?) points "
                "along it and mirroring would reverse it; expected a symmetric axis"
            )


def mirror_batch(
    batch: Batch,
    axes: Sequence[int],
    bounds: Sequence[Sequence[float]] | None,
    rng: np.random.Generator,
) -> Batch:
    """`batch` with each graph mirrored along each of `axes` with probability 1/2, drawn from
    `rng` (graph by graph, axis by axis). The mirror is the box's centre plane when the scene
    has bounds (so walls stay walls), else the plane through 0 (any plane will do: the model
    sees only relative positions and velocities then)."""
    flips = rng.random((batch.num_graphs, len(axes))) < 0.5
    if not flips.any():
        return batch
    positions = batch.positions.copy()
    obstacles = None if batch.obstacles is None else [list(o) for o in batch.obstacles]
    ends = np.cumsum(batch.n_node)
    starts = ends - batch.n_node
    for g, (start, end) in enumerate(zip(starts, ends, strict=True)):
        for k, axis in enumerate(axes):
            if flips[g, k]:
                centre_twice = 0.0 if bounds is None else bounds[axis][0] + bounds[axis][1]
                positions[:, start:end, axis] = centre_twice - positions[:, start:end, axis]
                if obstacles is not None:  # the obstacles are part of the scene mirrored
                    obstacles[g] = [_mirrored(v, axis, centre_twice) for v in obstacles[g]]
    mirrored = None if obstacles is None else tuple(tuple(o) for o in obstacles)
    return dataclasses.replace(batch, positions=positions, obstacles=mirrored)


def _mirrored(vertices: np.ndarray, axis: int, centre_twice: float) -> np.ndarray:
    out = vertices.copy()
    out[:, axis] = centre_twice - out[:, axis]
    return out

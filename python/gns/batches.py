"""Batches of windows as the model's tensors: the one conversion training and evaluation share.

gns.data.windows makes a Batch (time-major numpy, no torch); the simulator wants particle-major
tensors on its device. Kept apart from gns.train and gns.evaluate so that neither imports the
other for it.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

import gns.ops as ops
from gns.data.windows import Batch

__all__ = ["batch_obstacles", "batch_tensors", "obstacle_shapes"]


def batch_tensors(batch: Batch, device: torch.device) -> dict[str, Tensor | None]:
    """A Batch (time-major numpy) as the simulator's particle-major tensors on `device`."""

    def tensor(x: np.ndarray | None) -> Tensor | None:
        return None if x is None else torch.from_numpy(np.ascontiguousarray(x)).to(device)

    positions = batch.positions.transpose(1, 0, 2)  # (N, C + 2, D)
    return {
        "position_sequence": tensor(positions[:, :-1]),
        "next_position": tensor(positions[:, -1]),
        "particle_type": tensor(batch.particle_type),
        "n_node": tensor(batch.n_node),
        "context": tensor(batch.step_context),
        "material_property": tensor(batch.material_property),
    }


def obstacle_shapes(polylines: tuple[np.ndarray, ...] | None) -> list[ops.Obstacle]:
    """A trajectory's obstacle polylines (gns.data.Trajectory.obstacles) as shapes."""
    return [ops.Obstacle.polyline(v) for v in polylines or ()]


def batch_obstacles(batch: Batch) -> list[list[ops.Obstacle]] | None:
    """Each graph's obstacle shapes (the simulator's `obstacles`), or None without any."""
    if batch.obstacles is None:
        return None
    return [obstacle_shapes(polylines) for polylines in batch.obstacles]

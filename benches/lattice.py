"""The benchmarks' synthetic scene: particles on a jittered square lattice in a walled box."""

from __future__ import annotations

import numpy as np
from gns.data import Trajectory
from gns.simulator import Scene

RADIUS = 0.015  # the paper's 2D connectivity radius


def lattice(n: int, frames: int) -> tuple[Scene, Trajectory]:
    """n particles of one type on a jittered square lattice of spacing R * sqrt(pi / 13), so 13
    neighbours (self included) within R inside the block and fewer along its sides, moving at
    small random velocities for `frames` frames, in a WaterDrop-like box [0.1, 0.9]^2 (wider
    when the block needs it) with walls."""
    rng = np.random.default_rng(n)
    spacing = RADIUS * np.sqrt(np.pi / 13)
    cols = int(np.ceil(np.sqrt(n)))
    ij = np.stack([np.arange(n) % cols, np.arange(n) // cols], axis=1)
    lo = 0.1
    hi = max(0.9, lo + 2 * RADIUS + cols * spacing)
    x0 = lo + RADIUS + spacing * (ij + rng.uniform(-0.1, 0.1, (n, 2)))
    velocity = rng.normal(0.0, 1e-4, (n, 2))
    positions = (x0[None] + np.arange(frames)[:, None, None] * velocity[None]).astype(np.float32)
    scene = Scene(2, RADIUS, (5,), bounds=((lo, hi), (lo, hi)), walls=True)
    return scene, Trajectory(positions, np.full(n, 5), source="lattice")

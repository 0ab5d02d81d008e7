"""Does a sand model fall at g? One step of a block in free fall, far from every wall.

    python scripts/free_fall_probe.py MODEL [MODEL ...] [--corner 0.4 0.45] [--size 0.2]
        [--spacing 0.0078125] [--friction-angle 30] [--particle-type T]

MODEL: a model name, folder or checkpoint (as `gns rollout --run`). The block (a lattice of
`spacing`, `size` wide, lower-left corner at `corner`; the defaults are sand2d-taichi's block
and particle spacing) is given the model's C + 1 input frames of a throw upwards that reaches
its top at the last one, so it has been in free fall throughout. Every real simulator then
accelerates it at exactly g; the model's mean vertical acceleration over g is printed, with
that of the bottom and top rows (a bottom falling faster than the top squeezes the block
before it lands). A model that has learned gravity prints 1.00. The particles are of the
scene's one free (not kinematic) type unless --particle-type says which.
"""

from __future__ import annotations

import argparse
import math
from typing import Any

import gns
import numpy as np
import torch
from gns.mpm import lattice

GRAVITY = 9.81  # m/s^2, along -y


def thrown_block(block: np.ndarray, frames: int, g_step: float) -> np.ndarray:
    """(N, frames, 2) positions of `block` thrown up, at the top of the throw in the last frame:
    y_k = y - g k (k + 1) / 2 for k = -(frames - 1) ... 0, so each step's acceleration is -g and
    the last velocity is 0."""
    k = np.arange(-(frames - 1), 1)
    drop = -0.5 * g_step * k * (k + 1)
    return np.stack([block + [0.0, d] for d in drop], axis=1)


def fall_in_g(simulator: Any, block: np.ndarray, context: float | None, particle_type: int):
    """The block's vertical acceleration in one predicted step, over g: (mean, bottom row, top
    row); positive is downward."""
    g_step = GRAVITY * simulator.scene.dt**2  # the model steps dt = the data's frame spacing
    given = torch.tensor(
        thrown_block(block, simulator.config.model.velocity_history + 1, g_step),
        dtype=torch.float32,
    )
    history = given.double().numpy()  # what the model sees, rounded to float32
    with torch.no_grad():
        following = simulator.predict_positions(
            given,
            torch.full((len(block),), particle_type),
            context=None if context is None else torch.tensor([[context]], dtype=torch.float32),
        ).numpy()
    fall = -(following[:, 1] - 2 * history[:, -1, 1] + history[:, -2, 1]) / g_step
    y = block[:, 1]
    return fall.mean(), fall[y == y.min()].mean(), fall[y == y.max()].mean()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("models", nargs="+")
    parser.add_argument("--corner", type=float, nargs=2, default=[0.4, 0.45])
    parser.add_argument("--size", type=float, default=0.2)
    parser.add_argument("--spacing", type=float, default=1 / 128)
    parser.add_argument("--friction-angle", type=float, default=30.0)
    parser.add_argument("--particle-type", type=int)
    args = parser.parse_args()
    torch.set_num_threads(1)
    block = lattice(args.corner, (args.size, args.size), args.spacing)
    for name in args.models:
        simulator = gns.load_simulator(name).eval()
        scene = simulator.scene
        if scene.dim != 2 or scene.dt is None:
            raise SystemExit(f"{name}: the probe needs a 2D model that records its step (dt)")
        if scene.bounds is not None and not all(
            lo <= c and c + args.size <= hi
            for c, (lo, hi) in zip(args.corner, scene.bounds, strict=True)
        ):
            raise SystemExit(
                f"{name}: the block at {args.corner}, {args.size} wide, is not inside the "
                f"model's box {scene.bounds}; move it with --corner"
            )
        if scene.context_size > 1:
            raise SystemExit(f"{name}: context of {scene.context_size} values; the probe gives 1")
        # The friction angle is sand2d-taichi's context: tan(angle), one value.
        context = math.tan(math.radians(args.friction_angle)) if scene.context_size else None
        free = [t for t in scene.particle_types if t not in scene.kinematic_particle_types]
        particle_type = args.particle_type
        if particle_type is None:
            if len(free) != 1:
                raise SystemExit(f"{name}: free particle types {free}; say which: --particle-type")
            particle_type = free[0]
        mean, bottom, top = fall_in_g(simulator, block, context, particle_type)
        print(f"{name}: falls at {mean:.2f} g (bottom row {bottom:.2f} g, top row {top:.2f} g)")


if __name__ == "__main__":
    main()

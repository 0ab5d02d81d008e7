"""Does a sand model fall at g? One step of a block in free fall, far from every wall.

    python scripts/free_fall_probe.py MODEL [MODEL ...] [--corner X Y [Z]] [--size 0.2]
        [--spacing 0.0078125] [--friction-angle 30] [--particle-type T] [--speed 0]
        [--noise STD [--draws 32]] [--kick D]

MODEL: a model name, folder or checkpoint (as `gns rollout --run`). The block (a square, in 3D
a cube, lattice of `spacing`, `size` wide, its lower corner at `corner`, by default in the
middle of the model's box; the size and spacing default to sand2d-taichi's block) is given the
model's C + 1 input frames of a throw upwards that reaches its top at the last one (or, with
--speed V, falling at V m/s there), so it has been in free fall throughout. Every real
simulator then accelerates it at exactly g; the model's mean vertical acceleration over g is
printed, with that of the bottom and top rows (a bottom falling faster than the top squeezes
the block before it lands). A model that has learned gravity prints 1.00. The particles are of
the scene's one free (not kinematic) type unless --particle-type says which. --noise STD: the
input given the random-walk noise of training at that std, the prediction averaged over
--draws draws and read against the clean input (the training target's mean is g in every
row: a model that has learned to undo its noise still prints 1.00). --kick D: also how much of
a kick of D (m per step) to the last input velocity of one particle in the middle of the
bottom, middle and top rows, out of the block and into it, the model undoes in one step (1:
all, as training's target asks of noise; 0: none, taken for motion).
"""

from __future__ import annotations

import argparse

import gns
import torch
from gns import probes
from gns.mpm import lattice
from gns.probes import fall_in_g  # noqa: F401 (tests call it through this script)


def falling_block(scene, args):
    """The block at --corner, or in the middle of the box; inside the box either way."""
    if args.corner is None:
        return probes.probe_block(scene, args.size, args.spacing)
    if len(args.corner) != scene.dim:
        raise ValueError(f"--corner {args.corner} needs the scene's {scene.dim} coordinates")
    outside = scene.bounds is not None and any(
        c < lo or c + args.size > hi for c, (lo, hi) in zip(args.corner, scene.bounds, strict=True)
    )
    if outside:
        raise ValueError(
            f"the block at {args.corner}, {args.size} wide, is not inside the model's box "
            f"{scene.bounds}; move it with --corner"
        )
    return lattice(args.corner, (args.size,) * scene.dim, args.spacing)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("models", nargs="+")
    parser.add_argument("--corner", type=float, nargs="+", help="default: the box's middle")
    parser.add_argument("--size", type=float, default=0.2)
    parser.add_argument("--spacing", type=float, default=1 / 128)
    parser.add_argument("--friction-angle", type=float, default=30.0)
    parser.add_argument("--particle-type", type=int)
    parser.add_argument(
        "--speed",
        type=float,
        default=0.0,
        help="m/s downward at the last input frame (default 0: the top of a throw, whose "
        "input velocities look almost at rest)",
    )
    parser.add_argument(
        "--noise", type=float, default=0.0, help="random-walk input noise std (default 0: none)"
    )
    parser.add_argument("--draws", type=int, default=32, help="noise draws averaged (default 32)")
    parser.add_argument(
        "--kick", type=float, help="also the share of a kick of this size the model undoes"
    )
    args = parser.parse_args()
    if args.noise < 0 or args.draws < 1:
        parser.error(f"--noise {args.noise} must be >= 0 and --draws {args.draws} >= 1")
    torch.set_num_threads(1)
    for name in args.models:
        try:
            simulator = gns.load_simulator(name).eval()
            block = falling_block(simulator.scene, args)
            context, particle_type = probes.probe_inputs(
                simulator, args.friction_angle, args.particle_type
            )
            mean, bottom, top = probes.fall_in_g(
                simulator, block, context, particle_type, args.speed, args.noise, args.draws
            )
            removed = None
            if args.kick is not None:
                removed = probes.kick_removed(
                    simulator, block, context, particle_type, args.kick, args.speed
                )
        except ValueError as err:
            raise SystemExit(f"{name}: {err}") from err
        print(f"{name}: falls at {mean:.2f} g (bottom row {bottom:.2f} g, top row {top:.2f} g)")
        if removed is not None:
            rows = ", ".join(f"{row} {o:.2f} / {i:.2f}" for row, (o, i) in removed.items())
            print(f"{name}: undoes of a kick of {args.kick:g} (out / in): {rows}")


if __name__ == "__main__":
    main()

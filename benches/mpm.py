"""Speed of the reference simulator (gns.mpm, MLS-MPM in Rust) and calibration of the presets.

    python benches/mpm.py [--quick] [--threads 1 2 auto] [--busy] [--frames 10] [--warmup 3]
    python benches/mpm.py --calibrate [--trajectories 16] [--workers 1]

Speed: a dam break, one block 0.4 wide and 0.5 high in the bottom-left corner of the walls
[0.1, 0.9]^2, of water or of sand, at 4 particles per cell. The particle count is set by
refining the grid (about 1k, 2k, 8k particles: grid 35, 50, 100), as a finer simulation of the
same scene would be; the substep count grows with it through the CFL bound. In 3D the same dam
break in a corner of the walls [0.1, 0.9]^3, a block 0.3 x 0.4 x 0.3 at 8 particles per cell,
of water, sand or goop (about 2.3k, 4.5k, 9.4k particles: grid 20, 25, 32). Per row: wall-clock
ms per frame (median over --frames frames after --warmup frames; perf_counter in Rust around
each frame), substeps per frame (mean over the timed frames) and ns per particle-substep. Each
thread count runs in its own subprocess with RAYON_NUM_THREADS set, because rayon's global pool
is sized once, at its first use; "auto" leaves it unset, so every frame runs on all cores or on
one, whichever gns.mpm.simulate timed faster. --busy keeps one core busy with another process.

Calibration: generates --trajectories train trajectories of the `waterdrop` and `sand` presets
with gns.mpm.generate (frame counts of the presets, seed 0) and prints their per-frame velocity and
acceleration std against the paper's datasets (../shared/design/reference-simulator.md), with the
ratio ours / paper; the design asks for every ratio within [1 / 1.5, 1.5].
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

SIZES = {1000: 35, 2000: 50, 8000: 100}  # particles: grid (dam break block at 4 per cell)
QUICK_SIZES = {300: 20, 1000: 35}
MATERIALS = ("water", "sand")
# 3D: particles: grid of the 0.3 x 0.4 x 0.3 block at 8 per cell (grid >= 20 keeps the walls
# at 0.1 two cells inside the domain, as the simulator requires).
SIZES_3D = {2300: 20, 4500: 25, 9400: 32}
QUICK_SIZES_3D = {2300: 20}
MATERIALS_3D = ("water", "sand", "goop")
# Per-frame statistics of the paper's data, from the design's calibration table.
PAPER = {
    "waterdrop": ("WaterDrop", (1.40e-3, 1.31e-3), (6.6e-5, 8.0e-5)),
    "sand": ("Sand", (2.20e-3, 2.67e-3), (2.58e-4, 2.96e-4)),
}


def parse_args() -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--quick", action="store_true", help="smaller sizes, fewer frames (smoke test)")
    p.add_argument(
        "--threads",
        nargs="+",
        default=["1", "2"],
        help="rayon thread counts, or auto: the pool of all cores with each frame's threads "
        "chosen by timing the frames (gns.mpm.simulate's default)",
    )
    p.add_argument("--busy", action="store_true", help="with another process spinning on one core")
    p.add_argument("--frames", type=int, help="timed frames per case (default 10; quick 3)")
    p.add_argument("--warmup", type=int, help="frames before timing (default 3; quick 1)")
    p.add_argument("--calibrate", action="store_true", help="preset statistics vs the paper's")
    p.add_argument("--trajectories", type=int, default=16, help="per preset, with --calibrate")
    p.add_argument("--workers", type=int, default=1, help="generate's threads, with --calibrate")
    p.add_argument("--worker", help=argparse.SUPPRESS)  # internal: JSON cases for one subprocess
    return p.parse_args()


# ---------------------------------------------------------------------------------------- speed


def dam_break(material: str, grid: int, dim: int = 2):
    from gns.mpm import Block, Goop, MpmScene, Sand, Water

    kind = {"water": Water, "sand": Sand, "goop": Goop}[material]()
    if dim == 3:
        block = Block(kind, lower=(0.1, 0.1, 0.1), size=(0.3, 0.4, 0.3))
        return MpmScene([block], grid=grid, particles_per_cell=8.0)
    block = Block(kind, lower=(0.1, 0.1), size=(0.4, 0.5))
    return MpmScene([block], grid=grid, particles_per_cell=4.0)


def run_cases(cases: list[dict]) -> None:
    """In the subprocess: time every case and print one JSON line each."""
    from gns.mpm import simulate

    for case in cases:
        scene = dam_break(case["material"], case["grid"], case["dim"])
        result = simulate(scene, case["warmup"] + case["frames"] + 1)
        seconds = result.seconds[case["warmup"] :]
        substeps = result.substeps[case["warmup"] :].astype(float)
        n = result.positions.shape[1]
        per_frame = float(np.median(seconds))
        ns = 1e9 * float(np.median(seconds / substeps)) / n
        row = {**case, "particles": n, "ms_per_frame": 1e3 * per_frame}
        row.update(substeps=float(substeps.mean()), ns_per_particle_substep=ns)
        print(json.dumps(row), flush=True)


def speed(args: argparse.Namespace) -> None:
    sizes = QUICK_SIZES if args.quick else SIZES
    frames = args.frames or (3 if args.quick else 10)
    warmup = args.warmup if args.warmup is not None else (1 if args.quick else 3)
    sizes_3d = QUICK_SIZES_3D if args.quick else SIZES_3D
    tables = {2: (MATERIALS, list(sizes.values())), 3: (MATERIALS_3D, list(sizes_3d.values()))}
    cases = [
        {"dim": dim, "material": m, "grid": grid, "frames": frames, "warmup": warmup}
        for dim, (materials, grids) in tables.items()
        for m in materials
        for grid in grids
    ]
    rows = []
    # Another program holding a core, as on a user's busy machine.
    spinner = subprocess.Popen([sys.executable, "-c", "while True: pass"]) if args.busy else None
    try:
        for threads in args.threads:
            env = dict(os.environ)
            env.pop("RAYON_NUM_THREADS", None)
            if threads != "auto":
                env["RAYON_NUM_THREADS"] = threads
            done = subprocess.run(
                [sys.executable, __file__, "--worker", json.dumps(cases)],
                env=env,
                capture_output=True,
                text=True,
            )
            if done.returncode:
                raise SystemExit(f"the {threads}-thread run failed:\n{done.stderr}")
            rows += [{**json.loads(line), "threads": threads} for line in done.stdout.splitlines()]
    finally:
        if spinner is not None:
            spinner.kill()
            spinner.wait()
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    scenes = {
        2: "2D dam break (block 0.4 x 0.5, 4 particles per cell)",
        3: "3D dam break (block 0.3 x 0.4 x 0.3, 8 particles per cell)",
    }
    for dim, (materials, grids) in tables.items():
        print(
            f"MLS-MPM {scenes[dim]}, frame dt 2.5 ms; median of {frames} frames after "
            f"{warmup}; {os.cpu_count()} CPUs, load {load:.1f}"
            + ("; one core busy with another process" if args.busy else "")
        )
        header = (
            f"{'material':<9} {'particles':>9} {'grid':>5} {'threads':>7} {'ms/frame':>9} "
            f"{'substeps':>8} {'ns/(p*substep)':>14} {'speed-up':>8}"
        )
        print(header)
        ours = [r for r in rows if r["dim"] == dim]
        base = {(r["material"], r["grid"]): r["ms_per_frame"] for r in ours if r["threads"] == "1"}
        for material in materials:
            for grid in grids:
                for r in (r for r in ours if r["material"] == material and r["grid"] == grid):
                    one = base.get((material, grid))
                    gain = f"{one / r['ms_per_frame']:.2f}" if one else "-"
                    print(
                        f"{material:<9} {r['particles']:>9} {grid:>5} {r['threads']:>7} "
                        f"{r['ms_per_frame']:>9.2f} {r['substeps']:>8.1f} "
                        f"{r['ns_per_particle_substep']:>14.1f} {gain:>8}"
                    )


# ---------------------------------------------------------------------------------- calibration


def calibrate(args: argparse.Namespace) -> None:
    from gns.data import open_dataset
    from gns.mpm.generate import generate

    print(
        f"per-frame statistics of {args.trajectories} generated train trajectories (seed 0) "
        "against the paper's; ratio = ours / paper, wanted within [0.67, 1.5]"
    )
    print(f"{'preset':<10} {'statistic':<8} {'axis':>4} {'ours':>10} {'paper':>10} {'ratio':>6}")
    with tempfile.TemporaryDirectory() as tmp:
        for preset, (name, vel_paper, acc_paper) in PAPER.items():
            start = time.perf_counter()
            out = Path(tmp) / preset
            generate(preset, out, args.trajectories, 0, 0, 0, args.workers, progress=False)
            metadata = open_dataset(out, "train").metadata
            assert metadata.vel_std is not None and metadata.acc_std is not None
            for stat, ours, paper in (
                ("vel_std", metadata.vel_std, vel_paper),
                ("acc_std", metadata.acc_std, acc_paper),
            ):
                for axis in range(2):
                    ratio = ours[axis] / paper[axis]
                    flag = "" if 1 / 1.5 <= ratio <= 1.5 else "  outside"
                    print(
                        f"{preset:<10} {stat:<8} {axis:>4} {ours[axis]:>10.3e} "
                        f"{paper[axis]:>10.3e} {ratio:>6.2f}{flag}"
                    )
            seconds = time.perf_counter() - start
            print(f"({preset}: {seconds:.0f} s for {args.trajectories} trajectories, vs {name})")


def main() -> None:
    args = parse_args()
    if args.worker:
        run_cases(json.loads(args.worker))
    elif args.calibrate:
        calibrate(args)
    else:
        speed(args)


if __name__ == "__main__":
    main()

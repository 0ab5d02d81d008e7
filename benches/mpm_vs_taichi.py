"""Our reference simulator against an independent one: every trajectory of
../shared/data/sand2d-taichi (Taichi-Elements MLS-MPM, Drucker-Prager sand) re-run by gns.mpm
from the same block, initial velocity, friction angle and wall friction.

    python benches/mpm_vs_taichi.py [--data ../shared/data/sand2d-taichi]

Per trajectory, at the last frame: the deposit's extent (rightmost minus leftmost x) and pile
height (99th percentile of y above the floor) for both, their ratio ours / Taichi, and our
wall-clock time for the whole run. Our particles sit on a lattice, Taichi's were sampled at
random, so the particle counts differ by a few percent.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
from gns.mpm import Block, MpmScene, Sand, simulate

DEFAULT = Path(__file__).resolve().parents[2] / "shared" / "data" / "sand2d-taichi"


def shape(positions: np.ndarray, floor: float) -> tuple[float, float]:
    """(extent, pile height) of the (N, 2) positions."""
    extent = float(positions[:, 0].max() - positions[:, 0].min())
    return extent, float(np.percentile(positions[:, 1], 99) - floor)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=DEFAULT)
    args = parser.parse_args()
    manifest = json.loads((args.data / "manifest.json").read_text())
    floor = manifest["bounds"][1][0]
    print(f"{'file':<12} {'angle':>5} {'thrown':>6} {'extent T':>9} {'ours':>7} {'ratio':>6} "
          f"{'height T':>9} {'ours':>7} {'ratio':>6} {'seconds':>8}")  # fmt: skip
    ratios = []
    for entry in manifest["trajectories"]:
        x, y, w, h = entry["cube"]
        sand = Sand(friction_angle_deg=entry["friction_angle_deg"])
        block = Block(sand, (x, y), (w, h), tuple(entry["initial_velocity"]))
        scene = MpmScene([block], wall_friction=manifest["wall_friction"])
        start = time.perf_counter()
        ours = simulate(scene, manifest["frames"]).positions[-1]
        seconds = time.perf_counter() - start
        with np.load(args.data / entry["file"], allow_pickle=True) as archive:
            theirs = archive["trajectory0"][0][-1]
        (e0, h0), (e1, h1) = shape(theirs, floor), shape(ours, floor)
        ratios.append((e1 / e0, h1 / h0))
        thrown = "yes" if any(entry["initial_velocity"]) else "no"
        print(f"{entry['file']:<12} {entry['friction_angle_deg']:>5} {thrown:>6} {e0:>9.3f} "
              f"{e1:>7.3f} {e1 / e0:>6.2f} {h0:>9.3f} {h1:>7.3f} {h1 / h0:>6.2f} "
              f"{seconds:>8.2f}")  # fmt: skip
    r = np.array(ratios)
    within = np.all(np.abs(r - 1.0) <= 0.15, axis=1)
    print(f"within 15% in both: {within.sum()} of {len(r)}; median ratio extent "
          f"{np.median(r[:, 0]):.3f}, height {np.median(r[:, 1]):.3f}")  # fmt: skip


if __name__ == "__main__":
    main()

"""Read throughput of the dataset layouts: MB/s of decoded arrays and training windows/s.

Converts shared/data/sand2d-taichi (24 real trajectories, 350 x 656 x 2) to each layout in a
temporary folder, then times reading every trajectory of every split (median of --repeat runs)
and streaming shuffled 6 + 1 frame training windows from the train split.

    PYTHONPATH=python python benches/read_throughput.py [--data PATH] [--repeat 3]
"""

from __future__ import annotations

import argparse
import os
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np
from gns.data import available_splits, convert, crc32c, open_dataset, training_windows

LAYOUTS = ("deepmind", "npz", "h5")
DEFAULT_DATA = Path(__file__).resolve().parents[2] / "shared/data/sand2d-taichi"


def time_read(folder: Path) -> tuple[float, int]:
    """Seconds to open every split and read every trajectory; decoded payload bytes."""
    start = time.perf_counter()
    payload = 0
    for split in available_splits(folder):
        for trajectory in open_dataset(folder, split):
            payload += trajectory.nbytes
    return time.perf_counter() - start, payload


def time_windows(folder: Path) -> tuple[float, int]:
    """Seconds to stream one epoch of shuffled training windows; window count."""
    dataset = open_dataset(folder, "train")
    start = time.perf_counter()
    count = sum(1 for _ in training_windows(dataset, shuffle_buffer_size=2000, seed=0))
    return time.perf_counter() - start, count


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA)
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()
    if not (args.data / "manifest.json").is_file() and not (args.data / "metadata.json").is_file():
        raise SystemExit(f"no dataset at {args.data}")

    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        sources = {"source (npz per file)": args.data}
        for layout in LAYOUTS:
            start = time.perf_counter()
            convert(args.data, Path(tmp) / layout, layout)
            print(f"converted to {layout:9s} in {time.perf_counter() - start:6.2f} s")
            sources[layout] = Path(tmp) / layout
        for name, folder in sources.items():
            reads = [time_read(folder) for _ in range(args.repeat)]
            seconds = statistics.median(r[0] for r in reads)
            payload = reads[0][1]
            windows = [time_windows(folder) for _ in range(args.repeat)]
            w_seconds = statistics.median(w[0] for w in windows)
            size = sum(
                f.stat().st_size
                for split in available_splits(folder)
                for f in open_dataset(folder, split).files
            )
            rows.append(
                (
                    name,
                    size / 1e6,
                    payload / 1e6 / seconds,
                    size / 1e6 / seconds,
                    windows[0][1] / w_seconds,
                )
            )

    blob = np.random.default_rng(0).integers(0, 256, 32_000_000, dtype=np.uint8).tobytes()
    start = time.perf_counter()
    crc32c(blob)
    crc_rate = len(blob) / 1e6 / (time.perf_counter() - start)

    print()
    header = ("on disk MB", "decoded MB/s", "file MB/s", "windows/s")
    print(f"{'layout':22s} " + " ".join(f"{h:>13s}" for h in header))
    for name, size, decoded, on_disk, wps in rows:
        print(f"{name:22s} {size:13.1f} {decoded:13.1f} {on_disk:13.1f} {wps:13.0f}")
    print(f"\ncrc32c (numpy lanes): {crc_rate:.0f} MB/s on 32 MB; cpus: {os.cpu_count()}")
    print("windows/s: one epoch of the train split through a 2000-window shuffle buffer")


if __name__ == "__main__":
    main()

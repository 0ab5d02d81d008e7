"""`gns stats`, `gns validate`, `gns convert`: argument parsing and printing only."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from gns.data.convert import TARGETS, convert
from gns.data.dataset import open_dataset
from gns.data.errors import DatasetError
from gns.data.stats import Statistics, compute_statistics
from gns.data.validate import validate_dataset
from gns.files import write_json_atomic


def register(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    """Add the dataset subcommands to the `gns` parser."""
    stats = sub.add_parser(
        "stats",
        help="per-frame velocity / acceleration statistics of the train split",
        description="Velocity = x_t - x_{t-1}, acceleration = v_{t+1} - v_t, per frame (never "
        "divided by dt), over non-kinematic particles of the chosen split.",
    )
    stats.add_argument("path", type=Path, help="dataset folder (or one data file)")
    stats.add_argument("--split", default="train")
    stats.add_argument(
        "--kinematic-types",
        type=int,
        nargs="*",
        default=None,
        help="particle types to leave out (default: the dataset's setting)",
    )
    stats.add_argument(
        "--write", action="store_true", help="store the statistics in PATH/metadata.json"
    )
    stats.set_defaults(handler=run_stats)

    validate = sub.add_parser(
        "validate",
        help="check a dataset against its metadata and print every problem",
    )
    validate.add_argument("path", type=Path)
    validate.set_defaults(handler=run_validate)

    conv = sub.add_parser(
        "convert",
        help="rewrite a dataset in another layout (atomically)",
        description="Several SRC are written one after another into each split (the same "
        "scene; a source named k times is written k times), the statistics computed anew.",
    )
    conv.add_argument("src", type=Path, nargs="+")
    conv.add_argument("dst", type=Path, help="new folder (must not exist, or be empty)")
    conv.add_argument("--to", required=True, choices=TARGETS)
    conv.add_argument("--splits", nargs="*", default=None, help="default: every split present")
    conv.add_argument(
        "--frame-stride",
        type=int,
        default=1,
        help="keep every k-th frame (dt times k); train keeps every phase as its own trajectory",
    )
    conv.set_defaults(handler=run_convert)


def _format_statistics(stats: Statistics) -> str:
    lines = [f"{'axis':>4} {'vel_mean':>13} {'vel_std':>13} {'acc_mean':>13} {'acc_std':>13}"]
    for axis in range(stats.vel_mean.shape[0]):
        lines.append(
            f"{axis:>4} {stats.vel_mean[axis]:>13.6e} {stats.vel_std[axis]:>13.6e} "
            f"{stats.acc_mean[axis]:>13.6e} {stats.acc_std[axis]:>13.6e}"
        )
    lines.append(f"samples: {stats.vel_count} velocities, {stats.acc_count} accelerations")
    if stats.context_mean is not None and stats.context_std is not None:
        lines.append(
            f"step_context: mean {stats.context_mean.tolist()} std {stats.context_std.tolist()}"
        )
    return "\n".join(lines)


def run_stats(args: argparse.Namespace) -> int:
    dataset = open_dataset(args.path, args.split, kinematic_particle_types=args.kinematic_types)
    stats = compute_statistics(
        dataset, dataset.metadata.kinematic_particle_types, dataset.metadata.period
    )
    print(
        f"{dataset.path} [{dataset.split}, {dataset.layout}, {len(dataset)} trajectories, "
        f"kinematic types {sorted(dataset.metadata.kinematic_particle_types)} left out]"
    )
    print(_format_statistics(stats))
    if args.write:
        target = args.path / "metadata.json" if args.path.is_dir() else None
        if target is None or not target.is_file():
            raise DatasetError(args.path, "--write needs a dataset folder with a metadata.json")
        raw = json.loads(target.read_text(encoding="utf-8"))
        updated = stats.apply_to(dataset.metadata).to_dict()
        for key in ("vel_mean", "vel_std", "acc_mean", "acc_std", "context_mean", "context_std"):
            if key in updated:
                raw[key] = updated[key]
        write_json_atomic(target, raw)
        print(f"wrote statistics to {target}")
    return 0


def run_validate(args: argparse.Namespace) -> int:
    problems = validate_dataset(args.path)
    for problem in problems:
        print(problem)
    if problems:
        print(f"{len(problems)} problem(s) found in {args.path}", file=sys.stderr)
        return 1
    print(f"{args.path}: OK")
    return 0


def run_convert(args: argparse.Namespace) -> int:
    counts = convert(
        args.src, args.dst, args.to, splits=args.splits, frame_stride=args.frame_stride
    )
    for split, count in counts.items():
        print(f"{split}: {count} trajectories")
    print(f"wrote {args.dst} ({args.to})")
    return 0

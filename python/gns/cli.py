"""The `gns` command line: thin argparse subcommands; the work lives in the modules they call."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="gns", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)
    # Each module that offers commands adds its own subparsers here.
    from gns.data import commands as data_commands

    data_commands.register(sub)

    train = sub.add_parser(
        "train",
        help="train a GNS on a dataset (train split; validates on valid)",
        description="Checkpoints, train.csv / valid.csv and TensorBoard logs go to --out. "
        "Several processes: torchrun --nproc_per_node K -m gns train ...",
    )
    train.add_argument("--data", type=Path, required=True, help="dataset folder")
    train.add_argument("--out", type=Path, required=True, help="run folder")
    train.add_argument("--config", type=Path, help="TOML settings (or a run's config.json)")
    train.add_argument("--steps", type=int, help="override train.steps")
    train.add_argument("--resume", action="store_true", help="continue the run in --out")
    train.add_argument("--device", default="auto", help="auto (default), cpu, cuda, cuda:1, ...")
    train.add_argument("--threads", type=int, help="torch CPU threads (default: torch's)")
    train.add_argument("--quiet", action="store_true", help="no progress line")
    train.set_defaults(run=run_train)
    return parser


def set_threads(threads: int | None) -> None:
    if threads is None:
        return
    if threads < 1:
        raise ValueError(f"--threads must be at least 1, got {threads}")
    import torch

    torch.set_num_threads(threads)


def run_train(args: argparse.Namespace) -> int:
    from gns.config import load_config
    from gns.train import train

    set_threads(args.threads)
    train(
        args.data,
        args.out,
        load_config(args.config) if args.config else None,
        steps=args.steps,
        resume=args.resume,
        device=args.device,
        progress=not args.quiet,
    )
    return 0


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return int(args.run(args) or 0)
    except ValueError as err:
        print(f"gns {args.command}: error: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())

"""`gns generate` and `gns demo`, which starts by generating a small dataset."""

from __future__ import annotations

import argparse
from pathlib import Path

from gns.cli.options import (
    add_runtime_options,
    non_negative_int,
    positive_int,
    positive_number,
    preset_name,
    set_threads,
    whole_number,
)


def add_generate(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    """Add `gns generate` to the `gns` parser."""
    from gns.mpm.generate import PRESETS

    gen = sub.add_parser(
        "generate",
        help="simulate a dataset with the reference MPM simulator (DeepMind layout)",
        description=f"Presets: {', '.join(PRESETS)} (see gns.mpm.presets). The dataset depends "
        "on the arguments and --seed only, not on --workers. An interrupted run is resumed by "
        "repeating the command: finished trajectories are kept in OUT.partial/ until the "
        "dataset is complete.",
    )
    gen.add_argument("--preset", type=preset_name, required=True, help="scene preset")
    gen.add_argument("--out", type=Path, required=True, help="new dataset folder")
    gen.add_argument("--n-train", type=positive_int, required=True, help="train trajectories")
    gen.add_argument(
        "--n-valid", type=non_negative_int, default=0, help="valid trajectories (default 0)"
    )
    gen.add_argument(
        "--n-test", type=non_negative_int, default=0, help="test trajectories (default 0)"
    )
    gen.add_argument("--seed", type=non_negative_int, default=0)
    gen.add_argument(
        "--workers", type=positive_int, help="trajectories simulated at once (default: CPU count)"
    )
    gen.add_argument(
        "--frames",
        # Three frames are the fewest with an acceleration, as gns.mpm.generate requires.
        type=whole_number(3),
        help="frames per trajectory, frame 0 included (default: preset's)",
    )
    gen.add_argument(
        "--scale",
        type=positive_number(),
        default=1.0,
        help="about this many times the preset's particles: the grid and the lattice finer by "
        "scale^(1/D), the connectivity radius with them (default 1; about 5 gives the paper's "
        "3D sizes)",
    )
    gen.add_argument("--quiet", action="store_true", help="no progress line")
    gen.set_defaults(handler=run_generate)


def add_demo(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    """Add `gns demo` to the `gns` parser."""
    from gns.demo import SIZES

    demo = sub.add_parser(
        "demo",
        help="generate a small dataset, fine-tune the shipped model and train one from scratch "
        "for minutes, write the report (all on CPU)",
        description="OUT/data (gns generate), OUT/finetune (the shipped model of the preset's "
        "scenes fine-tuned, time-limited: gns train --init-from), OUT/scratch (a small GNS from "
        "scratch, as long), OUT/report (gns report on the test split: the shipped model, its "
        "fine-tuning and the model from scratch; the headline chosen on the valid split). "
        "Repeating the command resumes. The default (size small) takes about 10 minutes on an "
        "idle 2-core CPU.",
    )
    demo.add_argument("--out", type=Path, default=Path("demo"), help="default: ./demo")
    demo.add_argument(
        "--preset",
        type=preset_name,
        default="sand-taichi",
        help="gns generate preset (default sand-taichi, the shipped sand2d-taichi model's "
        "scenes; a preset without a shipped model trains from scratch only)",
    )
    demo.add_argument("--size", choices=list(SIZES), default="small", help="default small")
    demo.add_argument(
        "--train-minutes",
        type=positive_number("minutes"),
        help="each training's time (default: the size's)",
    )
    demo.add_argument("--steps", type=positive_int, help="at most this many steps in each training")
    demo.add_argument(
        "--trajectories",
        type=positive_int,
        nargs=3,
        metavar=("TRAIN", "VALID", "TEST"),
        help="trajectories per split (default: the size's)",
    )
    demo.add_argument(
        "--frames",
        # gns.demo's minimum: the model's 6 input frames and a few to roll out.
        type=whole_number(8),
        help="frames per trajectory (default: the size's)",
    )
    demo.add_argument("--seed", type=non_negative_int, default=0)
    demo.add_argument(
        "--workers", type=positive_int, help="simulations at once (default: CPU count)"
    )
    add_runtime_options(demo)
    demo.set_defaults(handler=run_demo)


def run_generate(args: argparse.Namespace) -> int:
    import os

    from gns.mpm.generate import generate

    summary = generate(
        args.preset,
        args.out,
        args.n_train,
        args.n_valid,
        args.n_test,
        seed=args.seed,
        workers=args.workers if args.workers is not None else os.cpu_count() or 1,
        frames=args.frames,
        progress=not args.quiet,
        scale=args.scale,
    )
    counts = ", ".join(f"{n} {split}" for split, n in summary.counts.items())
    reused = f", {summary.reused} from an interrupted run" if summary.reused else ""
    print(
        f"wrote {args.out}: {counts} trajectories ({summary.redrawn} draws rejected and "
        f"redrawn{reused}) in {summary.seconds:.1f} s"
    )
    return 0


def run_demo(args: argparse.Namespace) -> int:
    from gns.demo import demo

    set_threads(args.threads)
    demo(
        args.out,
        preset=args.preset,
        size=args.size,
        train_minutes=args.train_minutes,
        steps=args.steps,
        trajectories=None if args.trajectories is None else tuple(args.trajectories),
        frames=args.frames,
        seed=args.seed,
        device=args.device,
        workers=args.workers,
        command=args.command_line,
    )
    return 0

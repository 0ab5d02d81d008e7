"""`gns report`: rollout error against run time per frame, the learnt models beside the
reference simulator and the baselines."""

from __future__ import annotations

import argparse
from collections.abc import Callable
from pathlib import Path

from gns.cli.options import (
    RUN_HELP,
    ArgumentProblem,
    add_runtime_options,
    existing_path,
    model_path,
    non_negative_int,
    positive_int,
    set_threads,
)


def add_report(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    """Add `gns report` to the `gns` parser."""
    rep = sub.add_parser(
        "report",
        help="rollout error against run time per frame: GNS, the reference simulator, baselines",
        description="Rolls out each checkpoint on the split (timed; GNS and CConv checkpoints "
        "alike, one row each, named by their model), re-runs the reference MPM "
        "simulator at native and cheaper settings when the dataset was made by `gns generate` "
        "or is a manifest folder (sand2d-taichi's layout; re-run from the data's frame 0), "
        "scores them and the constant-velocity and static baselines (MSE, optimal transport, "
        "MMD at several horizons; where the sand stops and how high it piles in the last "
        "frame over the ground truth's: runout ratio, the 99th minus the 1st percentile of x; "
        "height ratio, the 99th percentile of y above the box's floor; density ratio, "
        "neighbours within the connectivity radius, and density ratio max, that ratio at its "
        "worst frame), and writes report.md / report.html, "
        "table.{md,csv,json}, error_vs_time.png, error_over_time.png, fronts.png, a GIF of one "
        "rollout and VTK files to --out. Every row is scored on the frames the models step "
        "between: every k-th frame of data whose frames are k times finer (as `gns rollout` "
        "takes them), and its time is per such frame.",
    )
    rep.add_argument("--run", type=model_path, required=True, help=RUN_HELP)
    rep.add_argument("--data", type=existing_path, required=True, help="dataset folder")
    rep.add_argument("--split", default="test")
    rep.add_argument(
        "--checkpoint",
        nargs="+",
        default=["auto"],
        metavar="auto|best|latest|PATH",
        help="one row per checkpoint (default auto: best when the run was validated)",
    )
    rep.add_argument(
        "--out", type=Path, help="default: RUN/report_SPLIT (a model folder: ./NAME/report_SPLIT)"
    )
    rep.add_argument(
        "--trajectories", type=positive_int, metavar="N", help="the first N (default all)"
    )
    rep.add_argument(
        "--horizons",
        nargs="+",
        help="frames from the first prediction, or full (default: 1 10 50 full, "
        "gns.report.REPORT_HORIZONS)",
    )
    rep.add_argument(
        "--every",
        type=positive_int,
        metavar="K",
        help="optimal transport and MMD on every K-th predicted frame (default 10)",
    )
    rep.add_argument(
        "--mpm",
        nargs="+",
        default=["auto"],
        metavar="SETTING",
        help="reference simulator rows: auto (native, half grid, twice cfl, both), native, "
        "grid=N, cfl=X, grid=N,cfl=X, or none",
    )
    rep.add_argument(
        "--animation-frames",
        type=non_negative_int,
        default=120,
        help="frames in the GIF (0: none)",
    )
    rep.add_argument(
        "--vtk-every",
        type=non_negative_int,
        help="VTK frame stride (0: none; default: about 100 frames)",
    )
    rep.add_argument(
        "--rest-steps",
        type=non_negative_int,
        default=0,
        metavar="K",
        help="also hold each trajectory's last frame still and roll every checkpoint out K "
        "steps from it: does a settled pile stay put and keep its packing "
        "(gns.evaluate.rest_test)? 0: skip (default)",
    )
    add_runtime_options(rep)
    rep.add_argument("--quiet", action="store_true", help="no progress lines")
    rep.set_defaults(handler=run_report)


def check_with(flag: str, parse: Callable[[list[str]], object], values: list[str]) -> None:
    """ArgumentProblem naming `flag` when `parse` (a parser of the module that reads the
    values) refuses them: checked here, before the work, not when the module gets to them."""
    try:
        parse(values)
    except ValueError as err:
        raise ArgumentProblem(flag, str(err)) from None


def run_report(args: argparse.Namespace) -> int:
    from gns.report import (
        DEFAULT_EVERY,
        REPORT_HORIZONS,
        parse_horizons,
        parse_mpm_variants,
        report,
    )

    if args.horizons is not None:
        check_with("--horizons", parse_horizons, args.horizons)
    # The native grid and CFL number only size the "auto" variants: any valid pair checks the
    # settings here, before report() reads the dataset's own and starts rolling out.
    check_with("--mpm", lambda specs: parse_mpm_variants(specs, 20, 0.5), args.mpm)
    set_threads(args.threads)
    report(
        args.run,
        args.data,
        split=args.split,
        checkpoints=args.checkpoint,
        out=args.out,
        trajectories=args.trajectories,
        horizons=REPORT_HORIZONS if args.horizons is None else args.horizons,
        every=DEFAULT_EVERY if args.every is None else args.every,
        mpm=args.mpm,
        animation_frames=args.animation_frames,
        vtk_every=args.vtk_every,
        rest_steps=args.rest_steps,
        device=args.device,
        progress=not args.quiet,
        command=args.command_line,
    )
    return 0

"""The `gns` command line: thin argparse subcommands; the work lives in the modules they call."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np


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
        "[model] kind = 'cconv' in the config trains the CConv baseline (section D.1) "
        "instead. Several processes: torchrun --nproc_per_node K -m gns train ...",
    )
    train.add_argument("--data", type=Path, required=True, help="dataset folder")
    train.add_argument("--out", type=Path, required=True, help="run folder")
    train.add_argument("--config", type=Path, help="TOML settings (or a run's config.json)")
    train.add_argument("--steps", type=int, help="override train.steps")
    train.add_argument("--resume", action="store_true", help="continue the run in --out")
    train.add_argument(
        "--time-limit",
        type=float,
        metavar="MINUTES",
        help="stop after this much wall-clock time with a checkpoint (--resume continues)",
    )
    add_runtime_options(train)
    train.add_argument("--quiet", action="store_true", help="no progress line")
    train.set_defaults(handler=run_train)

    roll = sub.add_parser(
        "rollout",
        help="autoregressive rollouts of a trained run on a split",
        description="One file per trajectory: rollout_{split}_{i}.npz (our schema) and, with "
        "--deepmind, rollout_{split}_{i}.pkl (DeepMind's layout). Prints the time per step "
        "split into graph building, features, model and integration.",
    )
    roll.add_argument("--run", type=Path, required=True, help="run folder or checkpoint file")
    roll.add_argument("--data", type=Path, required=True, help="dataset folder")
    roll.add_argument("--split", default="test")
    roll.add_argument("--out", type=Path, help="default: RUN/rollouts/SPLIT")
    roll.add_argument("--trajectories", type=int, nargs="*", help="indices (default: all)")
    roll.add_argument("--steps", type=int, help="frames to predict (default: all there are)")
    roll.add_argument("--deepmind", action="store_true", help="also write DeepMind pickles")
    roll.add_argument(
        "--float64",
        action="store_true",
        help="run the model and positions in float64 (to compare drift with float32)",
    )
    roll.add_argument(
        "--escape-distance",
        type=float,
        default=1.0,
        help="stop a rollout when a particle is farther outside the domain than this many "
        "times its longest side (default 1)",
    )
    add_checkpoint_option(roll)
    add_runtime_options(roll)
    roll.set_defaults(handler=run_rollout)

    ev = sub.add_parser(
        "eval",
        help="one-step and rollout metrics of a run next to the constant-velocity baseline",
        description="Reads the rollouts written by `gns rollout` (RUN/rollouts/SPLIT), computes "
        "MSE over time and at horizons, optimal transport and MMD (bandwidth 0.1) for the model "
        "and for the constant-velocity baseline, plus one-step MSE over the split's windows; "
        "writes RUN/eval_SPLIT.json.",
    )
    ev.add_argument("--run", type=Path, required=True, help="run folder")
    ev.add_argument("--data", type=Path, required=True, help="dataset folder")
    ev.add_argument("--split", default="test")
    ev.add_argument("--rollouts", type=Path, help="default: RUN/rollouts/SPLIT")
    ev.add_argument("--one-step-windows", type=int, default=512, help="0: skip one-step MSE")
    ev.add_argument("--every", type=int, default=1, help="OT and MMD on every k-th frame")
    ev.add_argument(
        "--rest-steps",
        type=int,
        default=0,
        help="also hold each trajectory's last frame still and roll the model out this many "
        "steps from it: does a settled pile keep its packing (gns.evaluate.rest_test)? 0: skip",
    )
    add_checkpoint_option(ev)
    add_runtime_options(ev)
    ev.set_defaults(handler=run_eval)

    gen = sub.add_parser(
        "generate",
        help="simulate a dataset with the reference MPM simulator (DeepMind layout)",
        description="Presets: waterdrop, water, sand, goop, multimaterial, ramps, continuous "
        "(see gns.generate). The dataset depends on the arguments and --seed only, not on "
        "--workers. An interrupted run is resumed by repeating the command: finished "
        "trajectories are kept in OUT.partial/ until the dataset is complete.",
    )
    gen.add_argument("--preset", required=True, help="scene preset")
    gen.add_argument("--out", type=Path, required=True, help="new dataset folder")
    gen.add_argument("--n-train", type=int, required=True, help="train trajectories")
    gen.add_argument("--n-valid", type=int, default=0, help="valid trajectories (default 0)")
    gen.add_argument("--n-test", type=int, default=0, help="test trajectories (default 0)")
    gen.add_argument("--seed", type=int, default=0)
    gen.add_argument(
        "--workers", type=int, help="trajectories simulated at once (default: CPU count)"
    )
    gen.add_argument(
        "--frames", type=int, help="frames per trajectory, frame 0 included (default: preset's)"
    )
    gen.add_argument("--quiet", action="store_true", help="no progress line")
    gen.set_defaults(handler=run_generate)

    rep = sub.add_parser(
        "report",
        help="rollout error against run time per frame: GNS, the reference simulator, baseline",
        description="Rolls out each checkpoint on the split (timed; GNS and CConv checkpoints "
        "alike, one row each, named by their model), re-runs the reference MPM "
        "simulator at native and cheaper settings when the dataset was made by `gns generate`, "
        "scores them and the constant-velocity baseline (MSE, optimal transport, MMD at "
        "several horizons), and writes report.md / report.html, table.{md,csv,json}, "
        "error_vs_time.png, error_over_time.png, a GIF of one rollout and VTK files to --out.",
    )
    rep.add_argument("--run", type=Path, required=True, help="run folder or checkpoint file")
    rep.add_argument("--data", type=Path, required=True, help="dataset folder")
    rep.add_argument("--split", default="test")
    rep.add_argument(
        "--checkpoint",
        nargs="+",
        default=["auto"],
        metavar="auto|best|latest|PATH",
        help="one row per checkpoint (default auto: best when the run was validated)",
    )
    rep.add_argument("--out", type=Path, help="default: RUN/report_SPLIT")
    rep.add_argument("--trajectories", type=int, metavar="N", help="the first N (default all)")
    rep.add_argument(
        "--horizons",
        nargs="+",
        default=["1", "10", "50", "full"],
        help="frames from the first prediction, or full (default: 1 10 50 full)",
    )
    rep.add_argument(
        "--every",
        type=int,
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
        "--animation-frames", type=int, default=120, help="frames in the GIF (0: none)"
    )
    rep.add_argument(
        "--vtk-every", type=int, help="VTK frame stride (0: none; default: about 100 frames)"
    )
    add_runtime_options(rep)
    rep.add_argument("--quiet", action="store_true", help="no progress lines")
    rep.set_defaults(handler=run_report)

    from gns.demo import SIZES

    demo = sub.add_parser(
        "demo",
        help="generate a small dataset, train a GNS for minutes, write the report (all on CPU)",
        description="OUT/data (gns generate), OUT/run (gns train, time-limited), OUT/report "
        "(gns report on the test split). Repeating the command resumes. The default (size "
        "small) takes about 5-10 minutes on a 2-core CPU.",
    )
    demo.add_argument("--out", type=Path, default=Path("demo"), help="default: ./demo")
    demo.add_argument("--preset", default="sand", help="gns generate preset (default sand)")
    demo.add_argument("--size", choices=list(SIZES), default="small", help="default small")
    demo.add_argument("--train-minutes", type=float, help="training time (default: the size's)")
    demo.add_argument("--steps", type=int, help="at most this many training steps")
    demo.add_argument(
        "--trajectories",
        type=int,
        nargs=3,
        metavar=("TRAIN", "VALID", "TEST"),
        help="trajectories per split (default: the size's)",
    )
    demo.add_argument("--frames", type=int, help="frames per trajectory (default: the size's)")
    demo.add_argument("--seed", type=int, default=0)
    demo.add_argument("--workers", type=int, help="simulations at once (default: CPU count)")
    add_runtime_options(demo)
    demo.set_defaults(handler=run_demo)
    return parser


def add_checkpoint_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--checkpoint",
        choices=("auto", "best", "latest"),
        default="auto",
        help="which checkpoint of a run folder: best (validation rollouts inside the box first, "
        "then the lowest validation rollout MSE), latest, "
        "or auto (default: best when the run was validated, otherwise latest)",
    )


def add_runtime_options(parser: argparse.ArgumentParser) -> None:
    """--device and --threads, shared by the commands that run the model."""
    parser.add_argument("--device", default="auto", help="auto (default), cpu, cuda, cuda:1, ...")
    parser.add_argument("--threads", type=int, help="torch CPU threads (default: torch's)")


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
        time_limit=None if args.time_limit is None else 60.0 * args.time_limit,
    )
    return 0


def run_folder(run: Path) -> Path:
    """Where outputs of `--run RUN` go: RUN itself, or the folder of a checkpoint file."""
    return run if run.is_dir() else run.parent


def run_rollout(args: argparse.Namespace) -> int:
    from gns.checkpoints import choose_checkpoint, load_simulator
    from gns.data import open_dataset
    from gns.device import resolve_device
    from gns.rollout import RolloutDiverged, rollout, save_deepmind_pickle, save_rollout

    set_threads(args.threads)
    device = resolve_device(args.device)
    checkpoint = choose_checkpoint(args.run, args.checkpoint)
    print(f"checkpoint {checkpoint}")
    simulator = load_simulator(checkpoint, device)
    if args.float64:
        simulator.double()
    dataset = open_dataset(args.data, args.split)
    out = args.out or run_folder(args.run) / "rollouts" / args.split
    out.mkdir(parents=True, exist_ok=True)
    indices = args.trajectories if args.trajectories else range(len(dataset))
    diverged = 0
    for i in indices:
        trajectory = dataset[i]
        info = {"dataset": str(args.data), "split": args.split, "checkpoint": str(checkpoint)}
        try:
            result = rollout(
                simulator,
                trajectory,
                num_steps=args.steps,
                metadata=info,
                escape_distance=args.escape_distance,
            )
        except RolloutDiverged as err:
            print(f"trajectory {i}: {err}", file=sys.stderr)
            result, diverged = err.rollout, diverged + 1
        stem = out / f"rollout_{args.split}_{i}"
        save_rollout(stem.with_suffix(".npz"), result)
        if args.deepmind:
            save_deepmind_pickle(stem.with_suffix(".pkl"), result)
        parts = "  ".join(f"{k} {1e3 * np.median(v):.2f}" for k, v in result.timings.items())
        total = 1e3 * np.median(sum(result.timings.values()))
        print(f"trajectory {i}: {result.num_steps} steps, ms/step (median) {total:.2f}: {parts}")
    print(f"wrote {len(indices)} rollouts to {out}")
    return 1 if diverged else 0


def run_eval(args: argparse.Namespace) -> int:
    from gns.checkpoints import choose_checkpoint, load_simulator
    from gns.data import open_dataset
    from gns.data.atomic import write_json_atomic
    from gns.device import resolve_device
    from gns.evaluate import evaluate_rollouts, one_step_errors, rest_test
    from gns.rollout import load_rollout

    if args.rest_steps < 0:
        raise ValueError(f"--rest-steps must be 0 (skip) or a step count, got {args.rest_steps}")
    set_threads(args.threads)
    folder = args.rollouts or run_folder(args.run) / "rollouts" / args.split
    files = sorted(
        folder.glob(f"rollout_{args.split}_*.npz"), key=lambda p: int(p.stem.split("_")[-1])
    )
    if not files:
        raise ValueError(f"no rollouts in {folder}; run `gns rollout --run {args.run} ...` first")
    rollouts = [load_rollout(f) for f in files]
    report = evaluate_rollouts(rollouts, distribution_every=args.every)
    if args.one_step_windows or args.rest_steps:
        device = resolve_device(args.device)
        # The figures of the model itself come from the checkpoint the rollouts were made
        # with, unless a checkpoint was asked for.
        made_with = {r.metadata.get("checkpoint") for r in rollouts}
        if args.checkpoint == "auto" and len(made_with) == 1 and None not in made_with:
            checkpoint = Path(str(made_with.pop()))
        else:
            checkpoint = choose_checkpoint(args.run, args.checkpoint)
        report["one_step_checkpoint"] = str(checkpoint)
        simulator = load_simulator(checkpoint, device)
        dataset = open_dataset(args.data, args.split)
    if args.one_step_windows:
        one_step = one_step_errors(
            simulator, list(dataset), max_windows=args.one_step_windows, device=device
        )
        for name, value in one_step.items():
            report["mean"][name]["one_step_mse"] = value
    if args.rest_steps:
        rest = [rest_test(simulator, t, args.rest_steps, device=device) for t in dataset]
        # The worst pile, not the mean one, for how far particles went.
        worst = ("max_displacement", "outside_box", "truth_speed")
        report["rest"] = {
            "steps": args.rest_steps,
            "trajectories": rest,
            "mean": {
                key: float((np.max if key in worst else np.mean)([r[key] for r in rest]))
                for key in rest[0]
            },
        }
    report["split"], report["rollouts"] = args.split, [str(f) for f in files]
    written = run_folder(args.run) / f"eval_{args.split}.json"
    write_json_atomic(written, report)
    mean = report["mean"]
    keys = [k for k in mean["model"] if k != "finite"] + ["finite"]
    print(f"{len(files)} rollouts of {args.split}; mean over trajectories (outside_box: worst)")
    print(f"{'metric':<16} {'model':>14} {'const. velocity':>16} {'ratio':>8}")
    for key in keys:
        a, b = mean["model"].get(key, np.nan), mean["constant_velocity"].get(key, np.nan)
        # Errors are compared as ratios; these figures are not errors.
        plain = key in ("finite", "outside_box", "density_ratio")
        ratio = b / a if a and np.isfinite(a) and not plain else np.nan
        print(f"{key:<16} {a:>14.4g} {b:>16.4g} {ratio:>8.3g}")
    if "ground_truth" in mean:
        print(f"(the ground truth itself: outside_box {mean['ground_truth']['outside_box']:.4g})")
    if "rest" in report:
        figures = ", ".join(f"{k} {v:.4g}" for k, v in report["rest"]["mean"].items())
        print(
            f"last frames held still for {args.rest_steps} steps (density_ratio: mean; "
            f"the others: worst): {figures}"
        )
    print(f"wrote {written}")
    return 0


def run_generate(args: argparse.Namespace) -> int:
    import os

    from gns.generate import generate

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
    )
    counts = ", ".join(f"{n} {split}" for split, n in summary.counts.items())
    reused = f", {summary.reused} from an interrupted run" if summary.reused else ""
    print(
        f"wrote {args.out}: {counts} trajectories ({summary.redrawn} draws rejected and "
        f"redrawn{reused}) in {summary.seconds:.1f} s"
    )
    return 0


def _command_line(argv: list[str] | None) -> str:
    import shlex

    return shlex.join(["gns", *(sys.argv[1:] if argv is None else argv)])


def run_report(args: argparse.Namespace) -> int:
    from gns.report import DEFAULT_EVERY, report

    set_threads(args.threads)
    report(
        args.run,
        args.data,
        split=args.split,
        checkpoints=args.checkpoint,
        out=args.out,
        trajectories=args.trajectories,
        horizons=args.horizons,
        every=DEFAULT_EVERY if args.every is None else args.every,
        mpm=args.mpm,
        animation_frames=args.animation_frames,
        vtk_every=args.vtk_every,
        device=args.device,
        progress=not args.quiet,
        command=args.command_line,
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


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    args.command_line = _command_line(argv)
    try:
        return int(args.handler(args) or 0)
    except ValueError as err:
        print(f"gns {args.command}: error: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())

"""The `gns` command line: thin argparse subcommands; the work lives in the modules they call."""

from __future__ import annotations

import argparse
import math
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np

from gns.data.errors import DatasetError

# What the work itself raises for a bad input (a missing or unreadable file, a dataset or
# checkpoint that is not one, a setting out of range): one line and exit status 2, not a
# traceback. DatasetError is a ValueError; it is named for the reader.
INPUT_ERRORS = (
    ValueError,
    DatasetError,
    FileNotFoundError,
    FileExistsError,
    IsADirectoryError,
    NotADirectoryError,
    PermissionError,
)


class ArgumentProblem(Exception):
    """An argument found wrong after parsing, once the files it refers to are open (e.g. a
    trajectory index past the split): reported like argparse's own errors, naming the flag."""

    def __init__(self, flag: str, message: str) -> None:
        super().__init__(f"argument {flag}: {message}")


# argparse types: a wrong value is refused while parsing, before any work, with an error that
# argparse prefixes with the flag ("argument --steps: must be a whole number >= 1, got 0").


def whole_number(minimum: int) -> Callable[[str], int]:
    """The argparse type of a whole number >= minimum."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            value = minimum - 1
        if value < minimum:
            raise argparse.ArgumentTypeError(f"must be a whole number >= {minimum}, got {text}")
        return value

    return parse


positive_int = whole_number(1)
non_negative_int = whole_number(0)


def positive_number(unit: str = "") -> Callable[[str], float]:
    """The argparse type of a finite number > 0 (of `unit`, named in the error)."""
    what = f"a positive number of {unit}" if unit else "a positive number"

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            value = math.nan
        if not (math.isfinite(value) and value > 0):
            raise argparse.ArgumentTypeError(f"must be {what}, got {text}")
        return value

    return parse


positive_float = positive_number()


def existing_path(text: str) -> Path:
    """The argparse type of a file or folder that exists (a dataset or a run is either)."""
    path = Path(text)
    if not path.exists():
        raise argparse.ArgumentTypeError(f"no such file or folder: {text}")
    return path


def model_path(text: str) -> Path:
    """The argparse type of --run: a run folder, checkpoint file or model folder that exists,
    or the name of a model shipped with gns (e.g. sand2d-taichi)."""
    from gns.checkpoints import model_location

    try:
        return model_location(text)
    except ValueError as err:
        raise argparse.ArgumentTypeError(str(err)) from None


def existing_file(text: str) -> Path:
    """The argparse type of a file that exists."""
    path = Path(text)
    if path.is_dir():
        raise argparse.ArgumentTypeError(f"{text} is a folder, not a file")
    if not path.is_file():
        raise argparse.ArgumentTypeError(f"no such file: {text}")
    return path


def existing_dir(text: str) -> Path:
    """The argparse type of a folder that exists."""
    path = Path(text)
    if path.exists() and not path.is_dir():
        raise argparse.ArgumentTypeError(f"{text} is a file, not a folder")
    if not path.is_dir():
        raise argparse.ArgumentTypeError(f"no such folder: {text}")
    return path


def preset_name(text: str) -> str:
    """The argparse type of --preset: a scene preset of gns.mpm.presets."""
    from gns.mpm.generate import PRESETS

    if text not in PRESETS:
        raise argparse.ArgumentTypeError(
            f"unknown preset {text!r}; expected one of {', '.join(PRESETS)}"
        )
    return text


def device_name(text: str) -> str:
    """The argparse type of --device: "auto" or a name torch knows (whether that device is
    present is gns.device.resolve_device's to say)."""
    if text == "auto":
        return text  # the default: no need to import torch while parsing
    import torch

    try:
        torch.device(text)
    except RuntimeError:
        raise argparse.ArgumentTypeError(
            f"expected auto, cpu, cuda, cuda:N or another torch device, got {text}"
        ) from None
    return text


RUN_HELP = "run folder, checkpoint file, model folder or shipped model name (e.g. sand2d-taichi)"


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
    train.add_argument("--data", type=existing_path, required=True, help="dataset folder")
    train.add_argument("--out", type=Path, required=True, help="run folder")
    train.add_argument(
        "--valid-data",
        type=existing_path,
        help="validate on this dataset's valid split (default: --data's); its frames may be a "
        "whole factor finer than --data's",
    )
    train.add_argument(
        "--config", type=existing_file, help="TOML settings (or a run's config.json)"
    )
    train.add_argument("--steps", type=positive_int, help="override train.steps")
    train.add_argument("--resume", action="store_true", help="continue the run in --out")
    train.add_argument(
        "--init-from",
        type=model_path,
        metavar="MODEL",
        help="fine-tune: start from this model's weights (" + RUN_HELP + "); --config may "
        "change only [noise] and [train]",
    )
    train.add_argument(
        "--time-limit",
        type=positive_number("minutes"),
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
        "split into graph building, features, model and integration. A model steps as far as "
        "its training data's frames were apart: on data whose frames are a whole factor k "
        "finer it rolls out on every k-th frame from frame 0 (the frames `gns convert "
        "--frame-stride k` keeps; the files record frame_stride and dataset_dt), and data "
        "whose frame spacing does not divide its step is refused.",
    )
    roll.add_argument("--run", type=model_path, required=True, help=RUN_HELP)
    roll.add_argument("--data", type=existing_path, required=True, help="dataset folder")
    roll.add_argument("--split", default="test")
    roll.add_argument("--out", type=Path, help="default: RUN/rollouts/SPLIT")
    roll.add_argument(
        "--trajectories", type=non_negative_int, nargs="*", help="indices (default: all)"
    )
    roll.add_argument(
        "--steps", type=positive_int, help="frames to predict (default: all there are)"
    )
    roll.add_argument("--deepmind", action="store_true", help="also write DeepMind pickles")
    roll.add_argument(
        "--float64",
        action="store_true",
        help="run the model and positions in float64 (to compare drift with float32)",
    )
    roll.add_argument(
        "--escape-distance",
        type=positive_float,
        default=1.0,
        help="stop a rollout when a particle is farther outside the domain than this many "
        "times its longest side (default 1)",
    )
    add_checkpoint_option(roll)
    add_runtime_options(roll)
    roll.set_defaults(handler=run_rollout)

    ev = sub.add_parser(
        "eval",
        help="one-step and rollout metrics of a run next to the constant-velocity and static "
        "baselines, with where the sand stops and how high it piles",
        description="Reads the rollouts written by `gns rollout` (RUN/rollouts/SPLIT), computes "
        "MSE over time and at horizons, optimal transport and MMD (bandwidth 0.1) for the model "
        "and for two baselines, constant velocity (every particle keeps its last velocity) and "
        "static (every particle stays where the last input frame has it), plus one-step MSE over "
        "the split's windows. The deposit, over the non-kinematic particles of the last frame, "
        "for the model, both baselines and the ground truth: runout, the 99th minus the 1st "
        "percentile of x (how wide the sand lies); pile_height, the 99th percentile of y minus "
        "the floor (the box's lower y bound, else the ground truth's lowest y at frame 0); "
        "neighbours, the mean count of other particles within the connectivity radius; and "
        "runout_ratio, height_ratio, density_ratio, each over the ground truth's (1 is right). "
        "Percentiles interpolate linearly between sorted values. The fronts (1st and 99th "
        "percentile of x in every frame) go to the JSON as front_x_p1 and front_x_p99. Means "
        "are over trajectories (outside_box: the worst). The one-step errors and the rest test "
        "take every k-th frame of data whose frames are k times finer than the model's step, "
        "as `gns rollout` does. Writes RUN/eval_SPLIT.json.",
    )
    ev.add_argument("--run", type=model_path, required=True, help=RUN_HELP)
    ev.add_argument("--data", type=existing_path, required=True, help="dataset folder")
    ev.add_argument("--split", default="test")
    ev.add_argument("--rollouts", type=existing_dir, help="default: RUN/rollouts/SPLIT")
    ev.add_argument(
        "--one-step-windows", type=non_negative_int, default=512, help="0: skip one-step MSE"
    )
    ev.add_argument("--every", type=positive_int, default=1, help="OT and MMD on every k-th frame")
    ev.add_argument(
        "--rest-steps",
        type=non_negative_int,
        default=0,
        help="also hold each trajectory's last frame still and roll the model out this many "
        "steps from it: does a settled pile keep its packing (gns.evaluate.rest_test)? 0: skip",
    )
    add_checkpoint_option(ev)
    add_runtime_options(ev)
    ev.set_defaults(handler=run_eval)

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
        "neighbours within the connectivity radius), and writes report.md / report.html, "
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

    from gns.demo import SIZES

    demo = sub.add_parser(
        "demo",
        help="generate a small dataset, train a GNS for minutes, write the report (all on CPU)",
        description="OUT/data (gns generate), OUT/run (gns train, time-limited), OUT/report "
        "(gns report on the test split). Repeating the command resumes. The default (size "
        "small) takes about 5-10 minutes on a 2-core CPU.",
    )
    demo.add_argument("--out", type=Path, default=Path("demo"), help="default: ./demo")
    demo.add_argument(
        "--preset",
        type=preset_name,
        default="sand",
        help="gns generate preset (default sand)",
    )
    demo.add_argument("--size", choices=list(SIZES), default="small", help="default small")
    demo.add_argument(
        "--train-minutes",
        type=positive_number("minutes"),
        help="training time (default: the size's)",
    )
    demo.add_argument("--steps", type=positive_int, help="at most this many training steps")
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
    export = sub.add_parser(
        "export",
        help="write a run's model (weights only, a few MB) to a model folder",
        description="Writes OUT/model.pt: the weights, scene and statistics a rollout needs, "
        "without the optimizer state. `gns rollout --run OUT` and gns.load_simulator(OUT) "
        "read it; outputs of commands given a model folder go to a folder of its name in the "
        "working directory. --average N averages the parameters of the run's last N "
        "checkpoints instead of taking one.",
    )
    export.add_argument("--run", type=existing_path, required=True, help="run folder or file")
    add_checkpoint_option(export)
    export.add_argument("--average", type=positive_int, default=1, help="default 1 (no average)")
    export.add_argument("--out", type=Path, required=True, help="model folder")
    export.set_defaults(handler=run_export)
    # Problems found after parsing are reported through their command's parser (see main).
    for command in sub.choices.values():
        command.set_defaults(parser=command)
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
    parser.add_argument(
        "--device", type=device_name, default="auto", help="auto (default), cpu, cuda, cuda:1, ..."
    )
    parser.add_argument(
        "--threads",
        type=positive_int,
        help="torch CPU threads, fixed (default: one per core or one, whichever the steps run "
        "faster with, timed again when they slow down; see gns.threads)",
    )


def set_threads(threads: int | None) -> None:
    if threads is not None:
        from gns.threads import fix_threads

        fix_threads(threads)


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
        valid_data=args.valid_data,
        init_from=args.init_from,
    )
    return 0


def run_export(args: argparse.Namespace) -> int:
    from gns.checkpoints import MODEL_FILE, export_model

    state = export_model(args.run, args.out, args.checkpoint, args.average)
    steps = state.get("averaged_steps") or [state["step"]]
    what = (
        f"the average of steps {', '.join(map(str, steps))}"
        if len(steps) > 1
        else f"step {steps[0]}"
    )
    print(f"wrote {args.out / MODEL_FILE}: {what} of {args.run}")
    return 0


def run_rollout(args: argparse.Namespace) -> int:
    from gns.checkpoints import choose_checkpoint, load_simulator, run_folder
    from gns.data import at_frame_stride, describe_frame_stride, open_dataset
    from gns.device import resolve_device
    from gns.rollout import (
        RolloutDiverged,
        frame_stride_metadata,
        rollout,
        rollout_path,
        save_deepmind_pickle,
        save_rollout,
    )

    dataset = open_dataset(args.data, args.split)
    indices = args.trajectories if args.trajectories else range(len(dataset))
    past = [i for i in indices if i >= len(dataset)]
    if past:
        raise ArgumentProblem(
            "--trajectories",
            f"expected indices 0 to {len(dataset) - 1} (the {args.split} split has "
            f"{len(dataset)} trajectories), got {' '.join(map(str, past))}",
        )
    out = args.out or run_folder(args.run) / "rollouts" / args.split
    if out.exists() and not out.is_dir():
        raise ArgumentProblem("--out", f"{out} exists and is not a folder")
    set_threads(args.threads)
    device = resolve_device(args.device)
    checkpoint = choose_checkpoint(args.run, args.checkpoint)
    print(f"checkpoint {checkpoint}")
    simulator = load_simulator(checkpoint, device)
    # Refused here, before the first rollout and its folder, if the data's spacing does not
    # divide the model's step.
    stride = simulator.frame_stride_for(dataset.metadata)
    if stride > 1:
        print(describe_frame_stride(dataset.metadata.dt, stride))
    if args.float64:
        simulator.double()
    # Absolute, so that `gns eval` finds them from any working directory.
    info = {
        "dataset": str(args.data.resolve()),
        "split": args.split,
        "checkpoint": str(checkpoint.resolve()),
        **frame_stride_metadata(dataset.metadata.dt, stride),
    }
    diverged = 0
    for i in indices:
        stem = rollout_path(out, args.split, i, suffix="")
        note = None
        try:
            result = rollout(
                simulator,
                at_frame_stride(dataset[i], stride),
                num_steps=args.steps,
                metadata=info,
                escape_distance=args.escape_distance,
            )
        except RolloutDiverged as err:
            result, diverged = err.rollout, diverged + 1
            # What diverged is the library's to say, where the finite steps went is ours: its
            # closing clause about them ("; the N ... steps before it are ...") gives way.
            problem = str(err).split(f"; the {err.step} ")[0]
            note = (
                f"trajectory {i}: {problem}; the {err.step} finite steps before it are saved in "
                f"{stem.with_suffix('.npz')}"
            )
        # Made here, not before the loop: a rollout that refuses its arguments (e.g. --steps
        # beyond the trajectory) then leaves no empty folder behind.
        out.mkdir(parents=True, exist_ok=True)
        save_rollout(stem.with_suffix(".npz"), result)
        if args.deepmind:
            save_deepmind_pickle(stem.with_suffix(".pkl"), result)
        if note:
            print(note, file=sys.stderr)
        parts = "  ".join(f"{k} {1e3 * np.median(v):.2f}" for k, v in result.timings.items())
        total = 1e3 * np.median(sum(result.timings.values()))
        print(f"trajectory {i}: {result.num_steps} steps, ms/step (median) {total:.2f}: {parts}")
    print(f"wrote {len(indices)} rollouts to {out}")
    return 1 if diverged else 0


def run_eval(args: argparse.Namespace) -> int:
    from gns.checkpoints import (
        choose_checkpoint,
        is_of_run,
        load_simulator,
        recorded_checkpoint,
        run_folder,
    )
    from gns.data import at_frame_stride, describe_frame_stride, open_dataset
    from gns.device import resolve_device
    from gns.evaluate import (
        evaluate_rollouts,
        generalisation,
        one_step_errors,
        rest_summary,
        rest_test,
        summary_table,
    )
    from gns.files import write_json_atomic
    from gns.rollout import load_rollout, rollout_files

    set_threads(args.threads)
    folder = args.rollouts or run_folder(args.run) / "rollouts" / args.split
    files = rollout_files(folder, args.split)
    if not files:
        raise ValueError(f"no rollouts in {folder}; run `gns rollout --run {args.run} ...` first")
    rollouts = [load_rollout(f) for f in files]
    dataset = open_dataset(args.data, args.split)
    # The checkpoint and the dataset are checked before the metrics, which take the time.
    if args.one_step_windows or args.rest_steps:
        device = resolve_device(args.device)
        # The figures of the model itself come from the checkpoint the rollouts were made
        # with, unless a checkpoint was asked for.
        made_with = {r.metadata.get("checkpoint") for r in rollouts}
        if args.checkpoint == "auto" and len(made_with) == 1 and None not in made_with:
            checkpoint = recorded_checkpoint(str(made_with.pop()), args.run)
            if not is_of_run(checkpoint, args.run):
                raise ValueError(
                    f"the rollouts in {folder} were made with {checkpoint}, which is not "
                    f"--run {args.run}'s: their one-step errors and rest test would be another "
                    f"model's; roll {args.run} out first (gns rollout) or pass the rollouts' own "
                    "--run"
                )
        else:
            checkpoint = choose_checkpoint(args.run, args.checkpoint)
        simulator = load_simulator(checkpoint, device)
        # One-step errors and the rest test on the frames the model steps between, as its
        # rollouts were made (gns rollout): every stride-th frame of the data.
        stride = simulator.frame_stride_for(dataset.metadata)
        made_at = {r.metadata.get("frame_stride") for r in rollouts} - {None}
        if made_at and made_at != {stride}:
            raise ValueError(
                f"the rollouts in {folder} were made at frame stride "
                f"{' and '.join(map(str, sorted(made_at)))}, but {checkpoint} takes frame stride "
                f"{stride} on {args.data} ({describe_frame_stride(dataset.metadata.dt, stride)}): "
                "its one-step errors and rest test would be of other frames than the rollouts'; "
                "use --checkpoint auto (the rollouts' own) or roll this one out again"
            )
        trajectories = [at_frame_stride(t, stride) for t in dataset]
    report = evaluate_rollouts(rollouts, distribution_every=args.every)
    if args.one_step_windows or args.rest_steps:
        report["one_step_checkpoint"] = str(checkpoint.resolve())
        report["frame_stride"] = stride
    if args.one_step_windows:
        one_step = one_step_errors(
            simulator, trajectories, max_windows=args.one_step_windows, device=device
        )
        for name, value in one_step.items():
            report["mean"][name]["one_step_mse"] = value
    if args.rest_steps:
        rest = [rest_test(simulator, t, args.rest_steps, device=device) for t in trajectories]
        report["rest"] = rest_summary(rest, args.rest_steps)
    report["split"], report["rollouts"] = args.split, [str(f.absolute()) for f in files]
    written = run_folder(args.run) / f"eval_{args.split}.json"
    # A model folder's outputs go to ./NAME, which --rollouts from elsewhere did not make.
    written.parent.mkdir(parents=True, exist_ok=True)
    band = generalisation(report, rollouts, dataset.metadata.extra.get("generator"))
    if band is not None:
        from gns.plots import error_against_parameter

        report["generalisation"] = band
        figure = written.with_name(f"generalisation_{args.split}.png")
        errors = {
            "GNS": np.array(band["model"]),
            "constant velocity": np.array(band["constant_velocity"]),
        }
        error_against_parameter(np.array(band["angle"]), errors, tuple(band["held_out"]), figure)
        inside = sum(band["in_band"])
        print(
            f"{inside} of {len(band['angle'])} trajectories in the band held out of training "
            f"({band['held_out'][0]:g}-{band['held_out'][1]:g} degrees): {figure}"
        )
    write_json_atomic(written, report)
    print(f"{len(files)} rollouts of {args.split}; mean over trajectories (outside_box: worst)")
    if report.get("frame_stride", 1) > 1:
        print(
            f"one-step errors and rest test: {describe_frame_stride(dataset.metadata.dt, stride)}"
        )
    print(summary_table(report["mean"]))
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


def _command_line(argv: list[str] | None) -> str:
    import shlex

    return shlex.join(["gns", *(sys.argv[1:] if argv is None else argv)])


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
    """Run `gns ARGV`; returns the exit status: 0, 1 (e.g. a rollout diverged) or 2 (misuse,
    with one error line on stderr and no traceback)."""
    try:
        args = build_parser().parse_args(argv)
    except SystemExit as stop:  # argparse's exit: 2 after an error, 0 after --help
        return int(stop.code or 0)
    args.command_line = _command_line(argv)
    try:
        return int(args.handler(args) or 0)
    except ArgumentProblem as err:
        args.parser.print_usage(sys.stderr)
        print(f"{args.parser.prog}: error: {err}", file=sys.stderr)
    except INPUT_ERRORS as err:
        print(f"gns {args.command}: error: {err}", file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main())

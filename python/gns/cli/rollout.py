"""`gns rollout` and `gns eval`: a model's rollouts on a split, and their metrics."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from gns.cli.options import (
    RUN_HELP,
    ArgumentProblem,
    add_checkpoint_option,
    add_precision_option,
    add_runtime_options,
    existing_dir,
    existing_path,
    model_path,
    non_negative_int,
    positive_float,
    positive_int,
    set_threads,
)


def add_rollout(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    """Add `gns rollout` to the `gns` parser."""
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
    roll.add_argument(
        "--enforce-walls",
        action=argparse.BooleanOptionalAction,
        help="put every particle that a step takes past a wall back on it, counting each "
        "correction in the file's metadata (default: the model's scene.enforce_walls)",
    )
    add_checkpoint_option(roll)
    add_runtime_options(roll)
    add_precision_option(roll)
    roll.set_defaults(handler=run_rollout)


def add_eval(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    """Add `gns eval` to the `gns` parser."""
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
        "pile_base, the 1st percentile of y minus the floor (sand resting on it: about 0); "
        "neighbours, the mean count of other particles within the connectivity radius; and "
        "runout_ratio, height_ratio, density_ratio, each over the ground truth's (1 is right); "
        "density_ratio_max, the largest of that density ratio over every frame (the packing at "
        "its worst, a landing). "
        "Percentiles interpolate linearly between sorted values. The fronts (1st and 99th "
        "percentile of x in every frame) go to the JSON as front_x_p1 and front_x_p99, the "
        "mean neighbour count of every frame as neighbours_by_frame. Means "
        "are over trajectories (outside_box: the worst). Rollouts made with the walls enforced "
        "add the model's wall_corrections (particle-steps put back on a wall) and "
        "wall_correction_max (the largest move, the worst). The one-step errors and the rest "
        "test take every k-th frame of data whose frames are k times finer than the model's step, "
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
    add_precision_option(ev)
    ev.set_defaults(handler=run_eval)


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
    if args.float64 and args.precision == "bf16":
        raise ArgumentProblem("--precision", "expected auto or fp32 with --float64, got bf16")
    set_threads(args.threads)
    device = resolve_device(args.device)
    checkpoint = choose_checkpoint(args.run, args.checkpoint)
    print(f"checkpoint {checkpoint}")
    simulator = load_simulator(checkpoint, device)
    if args.precision:
        simulator.model.precision = args.precision
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
                enforce_walls=args.enforce_walls,
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
        walls = ""
        if result.metadata["enforce_walls"]:
            walls = (
                f"; walls put back {result.metadata['wall_corrections']} particle-steps (at "
                f"most {result.metadata['wall_correction_max']:.3g})"
            )
        print(
            f"trajectory {i}: {result.num_steps} steps, ms/step (median) {total:.2f}: {parts}"
            + walls
        )
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
        if args.precision:
            simulator.model.precision = args.precision
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
    print(
        f"{len(files)} rollouts of {args.split}; mean over trajectories (outside_box, "
        "wall_correction_max: worst)"
    )
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

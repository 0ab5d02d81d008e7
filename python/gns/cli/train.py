"""`gns train` and `gns export`: making a model and writing it out."""

from __future__ import annotations

import argparse
from pathlib import Path

from gns.cli.options import (
    RUN_HELP,
    add_checkpoint_option,
    add_runtime_options,
    existing_file,
    existing_path,
    model_path,
    positive_int,
    positive_number,
    set_threads,
)


def add_train(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    """Add `gns train` to the `gns` parser."""
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


def add_export(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    """Add `gns export` to the `gns` parser."""
    export = sub.add_parser(
        "export",
        help="write a run's model (weights only, a few MB) to a model folder",
        description="Writes OUT/model.pt: the weights, scene and statistics a rollout needs, "
        "without the optimizer state. `gns rollout --run OUT` and gns.load_simulator(OUT) "
        "read it; outputs of commands given a model folder go to a folder of its name in the "
        "working directory. --average N averages the parameters of the run's last N "
        "checkpoints instead of taking one (they must be of one model: the same [model] and "
        "[scene]; how they were trained, [train] and [noise], may differ, as after a --resume "
        "with another --steps).",
    )
    export.add_argument("--run", type=existing_path, required=True, help="run folder or file")
    add_checkpoint_option(export)
    export.add_argument("--average", type=positive_int, default=1, help="default 1 (no average)")
    export.add_argument("--out", type=Path, required=True, help="model folder")
    export.add_argument(
        "--enforce-walls",
        action=argparse.BooleanOptionalAction,
        help="the model's rollouts put particles that a step takes past a wall back on it, "
        "each correction counted (scene.enforce_walls; default: as trained)",
    )
    export.set_defaults(handler=run_export)


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

    state = export_model(args.run, args.out, args.checkpoint, args.average, args.enforce_walls)
    steps = state.get("averaged_steps") or [state["step"]]
    what = (
        f"the average of steps {', '.join(map(str, steps))}"
        if len(steps) > 1
        else f"step {steps[0]}"
    )
    walls = " (walls enforced)" if state["config"]["scene"].get("enforce_walls") else ""
    print(f"wrote {args.out / MODEL_FILE}: {what} of {args.run}{walls}")
    return 0

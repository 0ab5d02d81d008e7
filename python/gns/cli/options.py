"""What the subcommands share: argparse types, the options of the commands that run a model,
and ArgumentProblem for an argument found wrong once its files are open."""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable
from pathlib import Path


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


def add_precision_option(parser: argparse.ArgumentParser) -> None:
    """--precision, for the commands whose figures a user compares across machines."""
    parser.add_argument(
        "--precision",
        choices=("auto", "fp32", "bf16"),
        help="what the network runs in: fp32, bf16 (autocast), or auto (bf16 only where it "
        "is native and timed faster, so figures can differ between machines and loads); "
        "default: the model's own (model.precision, usually auto)",
    )


def set_threads(threads: int | None) -> None:
    if threads is not None:
        from gns.threads import fix_threads

        fix_threads(threads)

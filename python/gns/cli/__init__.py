"""The `gns` command line: thin argparse subcommands; the work lives in the modules they call."""

from __future__ import annotations

import argparse
import sys

from gns.cli import generate, report, rollout, train
from gns.cli.options import ArgumentProblem
from gns.data.errors import DatasetError

# The subcommands live in this package's modules, a group of related commands each (the
# dataset ones in gns.data.commands); their handlers import the heavy modules (torch, the
# simulator) only when run, so that `gns --help` starts fast.

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


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="gns", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)
    # Each module that offers commands adds its own subparsers here, in the order that
    # `gns --help` lists them.
    from gns.data import commands as data_commands

    data_commands.register(sub)
    train.add_train(sub)
    rollout.add_rollout(sub)
    rollout.add_eval(sub)
    generate.add_generate(sub)
    report.add_report(sub)
    generate.add_demo(sub)
    train.add_export(sub)
    # Problems found after parsing are reported through their command's parser (see main).
    for command in sub.choices.values():
        command.set_defaults(parser=command)
    return parser


def _command_line(argv: list[str] | None) -> str:
    import shlex

    return shlex.join(["gns", *(sys.argv[1:] if argv is None else argv)])


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

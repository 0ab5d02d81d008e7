"""The `gns` command line: thin argparse subcommands; the work lives in the modules they call."""

from __future__ import annotations

import argparse
import sys


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="gns", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)
    # Each module that offers commands adds its own subparsers here.
    from gns.data import commands as data_commands

    data_commands.register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return int(args.run(args) or 0)
    except ValueError as err:
        print(f"gns {args.command}: error: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())

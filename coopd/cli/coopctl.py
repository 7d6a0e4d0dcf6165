"""coopctl: the command-line front end of coopd.

Each subcommand group lives in its own module with a `register(subparsers)` function that
adds its parser and sets `handler` (a function args -> exit code). To add a group (e.g. the
daemon's status, dump-map, peers, merge-now), write the module and list it in GROUPS.
"""

import argparse
import sys

from coopd.version import add_version_option

from . import daemon_commands, key_commands, map_tools

GROUPS = (map_tools, daemon_commands, key_commands)


class CommandError(Exception):
    """An expected failure of a subcommand: printed as one line, exit code 1."""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="coopctl", description="Control and inspect coopd and its maps.")
    add_version_option(parser)
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for group in GROUPS:
        group.register(sub)
    return parser


def main(argv=None) -> int:
    """Entry point of the coopctl script; returns the process exit code."""
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.handler(args) or 0)
    except (CommandError, OSError, ValueError) as e:
        print(f"coopctl: error: {e}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())

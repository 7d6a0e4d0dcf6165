"""coopctl: the command-line front end of coopd.

Each subcommand group lives in its own module with a `register(subparsers)` function that
adds its parser and sets `handler` (a function args -> exit code). To add a group (e.g. the
daemon's status, dump-map, peers, merge-now), write the module and list it in GROUPS.
Results, failures and exit codes: coopd.cli.output.
"""

import argparse
import json
import sys

from coopd.daemon.control import DaemonUnreachable, RemoteError
from coopd.version import add_version_option

from . import daemon_commands, key_commands, map_tools
from .output import FAILED, UNREACHABLE, CommandError, UsageError, describe, error_object, exit_table

GROUPS = (map_tools, daemon_commands, key_commands)


class Parser(argparse.ArgumentParser):
    """An ArgumentParser whose usage errors reach main (to be printed as JSON with --json)."""

    def error(self, message):
        raise UsageError(self.prog, message, self.format_usage())


def build_parser() -> argparse.ArgumentParser:
    parser = Parser(prog="coopctl", description="Control and inspect coopd and its maps.",
                    epilog=exit_table() + "\n\nWith --json every command prints one JSON object on stdout, "
                    'failures too: {"error": ..., "code": ..., "exit": ...}.',
                    formatter_class=argparse.RawDescriptionHelpFormatter)
    add_version_option(parser)
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for group in GROUPS:
        group.register(sub)
    return parser


def main(argv=None) -> int:
    """Entry point of the coopctl script; returns the process exit code."""
    argv = sys.argv[1:] if argv is None else list(argv)
    wants_json = "--json" in argv  # known before parsing, for usage errors
    try:
        args = build_parser().parse_args(argv)
        return int(args.handler(args) or 0)
    except UsageError as e:
        if not wants_json:  # as argparse prints it
            print(f"{e.usage}{e.prog}: error: {e.problem}", file=sys.stderr)
            return e.exit.code
        failure, extra, error = e.exit, {}, e
    except CommandError as e:
        failure, extra, error = e.exit, {}, e
    except DaemonUnreachable as e:
        failure, extra, error = UNREACHABLE, {}, e
    except RemoteError as e:
        failure, extra, error = FAILED, {"daemon_code": e.code}, e
    except (OSError, ValueError) as e:
        failure, extra, error = FAILED, {}, e
    except ImportError as e:  # an optional dependency the install left out (e.g. Pillow for PNG)
        if not getattr(e, "extra", None):
            raise
        failure, extra, error = FAILED, {"missing_extra": e.extra}, e
    message = describe(error)
    if wants_json:
        print(json.dumps(error_object(message, failure, **extra)))
    else:
        print(f"coopctl: error: {message}", file=sys.stderr)
    return failure.code


if __name__ == "__main__":
    sys.exit(main())

"""coopctl's results and failures: exit codes, `--json` output, error messages that name the file.

Every command prints either text or, with --json, exactly one JSON object on stdout: its result,
or on failure {"error": MESSAGE, "code": NAME, "exit": N}. The exit codes (EXITS) are shown by
`coopctl --help` and tabled in docs/operations.md.
"""

import contextlib
import json
import os
from dataclasses import dataclass


@dataclass(frozen=True)
class Exit:
    code: int
    name: str
    meaning: str


OK = Exit(0, "ok", "done")
FAILED = Exit(1, "failed", "the command failed: unreadable or invalid file, the daemon refused, "
                           "a write failed")
USAGE = Exit(2, "usage", "bad command line (an unknown option, output suffix or map name)")
NOT_MERGED = Exit(3, "not_merged", "map merge: at least one map could not be merged (the report says why)")
DEFERRED = Exit(4, "deferred", "merge-now: deferred, the merge does not fit the daemon's memory budget now")
UNREACHABLE = Exit(5, "unreachable", "coopd not running, its control socket not accessible, or no answer "
                                     "within --timeout")
EXITS = (OK, FAILED, USAGE, NOT_MERGED, DEFERRED, UNREACHABLE)


def exit_table() -> str:
    """The exit codes as coopctl --help shows them."""
    return "exit codes:\n" + "\n".join(f"  {e.code}  {e.name:<12} {e.meaning}" for e in EXITS)


class CommandError(Exception):
    """An expected failure of a subcommand: one line (or one JSON object) and its exit code."""

    def __init__(self, message: str, exit: Exit = FAILED):
        super().__init__(message)
        self.exit = exit


class UsageError(CommandError):
    """argparse's complaint about the command line (exit 2), with the parser's usage line."""

    def __init__(self, prog: str, problem: str, usage: str):
        super().__init__(f"{prog}: {problem}", USAGE)
        self.prog, self.problem, self.usage = prog, problem, usage


def add_json_option(parser, text: str = "print the result as one JSON object") -> None:
    parser.add_argument("--json", action="store_true", help=text)


def describe(error: BaseException) -> str:
    """One line for the operator; OSErrors as `FILE: reason` instead of `[Errno 2] ...: 'FILE'`."""
    if isinstance(error, OSError) and error.filename is not None and error.strerror:
        return f"{os.fsdecode(error.filename)}: {error.strerror}"
    return str(error) or type(error).__name__


@contextlib.contextmanager
def about_file(path):
    """Errors while handling `path` name it: a ValueError (a malformed file) becomes `PATH: reason`."""
    try:
        yield
    except ValueError as e:
        message = str(e)
        name = os.fspath(path)
        raise CommandError(message if message.startswith(f"{name}:") else f"{name}: {message}") from e


def emit(args, result: dict, text: str) -> None:
    """Print the command's result: `text`, or `result` as one JSON object with --json."""
    print(json.dumps(result) if getattr(args, "json", False) else text)


def error_object(message: str, exit: Exit, **extra) -> dict:
    """The JSON object a failing command prints with --json."""
    return {"error": message, "code": exit.name, "exit": exit.code, **extra}

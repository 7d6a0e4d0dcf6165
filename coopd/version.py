"""The version every command prints with --version.

An installed coopd reports its distribution's version (importlib.metadata). Run from a source
checkout (PYTHONPATH, or an editable install of another checkout) the metadata may describe a
different tree, so a pyproject.toml beside the imported package wins and is named in the answer.
"""

import argparse
import tomllib
from pathlib import Path

DISTRIBUTION = "coopd"
PACKAGE_DIR = Path(__file__).resolve().parent


def source_tree_version(package_dir: Path) -> str | None:
    """`VERSION (source tree DIR)` when `package_dir` sits in a coopd checkout, else None."""
    pyproject = package_dir.parent / "pyproject.toml"
    try:
        project = tomllib.loads(pyproject.read_text()).get("project", {})
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError):
        return None
    if project.get("name") != DISTRIBUTION or not isinstance(project.get("version"), str):
        return None
    return f"{project['version']} (source tree {package_dir.parent})"


def package_version(package_dir: Path = PACKAGE_DIR) -> str:
    """The version of the coopd that is running: source checkout, installed distribution, or unknown."""
    import importlib.metadata  # here, not at load: it costs every command's start, --version alone needs it

    found = source_tree_version(package_dir)
    if found is not None:
        return found
    try:
        return importlib.metadata.version(DISTRIBUTION)
    except importlib.metadata.PackageNotFoundError:
        return "unknown (not installed, no pyproject.toml beside the package)"


class _VersionAction(argparse.Action):
    """argparse's "version" action, with the version looked up only when --version is given."""

    def __init__(self, option_strings, dest=argparse.SUPPRESS, default=argparse.SUPPRESS, help=None):
        super().__init__(option_strings, dest, nargs=0, default=default,
                         help=help or "show the version and exit")

    def __call__(self, parser, namespace, values, option_string=None):
        print(f"{parser.prog} {package_version()}")
        parser.exit()


def add_version_option(parser) -> None:
    """`--version` on an argparse parser: prints `PROG VERSION` and exits 0."""
    parser.add_argument("--version", action=_VersionAction)

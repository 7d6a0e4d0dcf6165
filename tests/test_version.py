"""--version on coopd, coopctl and coopd-sim: the checkout's version from source, else the installed one."""

import importlib.metadata
import tomllib
from pathlib import Path

import pytest

from coopd.cli import coopctl
from coopd.daemon import main as daemon_main
from coopd.version import package_version, source_tree_version
from firmware_sim import cli as sim_cli

ROOT = Path(__file__).resolve().parents[1]
VERSION = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["version"]


def test_a_checkout_reports_its_own_pyproject_version():
    assert package_version() == f"{VERSION} (source tree {ROOT})"


def test_without_a_checkout_the_installed_distribution_answers(tmp_path):
    package = tmp_path / "site-packages" / "coopd"
    package.mkdir(parents=True)
    try:
        expected = importlib.metadata.version("coopd")
    except importlib.metadata.PackageNotFoundError:
        expected = "unknown (not installed, no pyproject.toml beside the package)"
    assert package_version(package) == expected


@pytest.mark.parametrize("text", ['[project]\nname = "other"\nversion = "9"\n', "[project\n", "\xff"])
def test_a_foreign_or_broken_pyproject_is_not_ours(tmp_path, text):
    (tmp_path / "pyproject.toml").write_text(text, encoding="latin-1")
    (tmp_path / "coopd").mkdir()
    assert source_tree_version(tmp_path / "coopd") is None


@pytest.mark.parametrize("main, prog", [(daemon_main.main, "coopd"), (coopctl.main, "coopctl"),
                                        (sim_cli.main, "coopd-sim")])
def test_every_command_prints_its_version(main, prog, capsys):
    with pytest.raises(SystemExit) as exit_:
        main(["--version"])
    assert exit_.value.code == 0
    assert capsys.readouterr().out == f"{prog} {VERSION} (source tree {ROOT})\n"

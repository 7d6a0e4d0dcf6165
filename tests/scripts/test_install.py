"""scripts/install refuses what it cannot do before it changes anything (its whole run, from the
wheel to the first start, is proven in tests/daemon/test_nspawn_boot.py)."""

import os
import shutil
import subprocess
from pathlib import Path

import pytest

INSTALL = Path(__file__).resolve().parents[2] / "scripts" / "install"


def run(*args, user=None):
    prefix = [] if user is None else ["setpriv", f"--reuid={user}", f"--regid={user}", "--clear-groups"]
    return subprocess.run(prefix + [str(INSTALL), *args], capture_output=True, text=True, timeout=60)


def test_help_names_the_one_command_and_its_options():
    r = run("--help")
    assert r.returncode == 0
    assert "scripts/install [--wheel FILE] [--extras LIST] [--prefix DIR]" in r.stdout
    assert "/opt/coopd" in r.stdout and "PEP 668" in r.stdout


@pytest.mark.parametrize("args, message", [
    (("--bogus",), "unknown argument --bogus"),
    (("--prefix", "relative/dir"), "--prefix must be an absolute path"),
])
def test_bad_arguments_stop_before_any_change(tmp_path, args, message):
    if os.geteuid() != 0 and "--prefix" in args:
        pytest.skip("the root check comes first")
    r = run(*args)
    assert r.returncode == 1 and message in r.stderr, r.stderr
    assert not Path("relative").exists()


def test_needs_root():
    if os.geteuid() != 0 and shutil.which("setpriv") is None:
        pytest.skip("needs root to drop to another user, or a non-root run")
    r = run("--prefix", "/nonexistent/coopd", user=65534 if os.geteuid() == 0 else None)
    assert r.returncode == 1 and "run as root" in r.stderr, r.stderr
    assert not Path("/nonexistent/coopd").exists()

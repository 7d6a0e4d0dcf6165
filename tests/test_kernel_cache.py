"""Where numba keeps coopd's compiled kernels: never a shared predictable temp path, and importing
coopd changes nothing in the environment."""

import os
import subprocess
import sys
from pathlib import Path

from coopd.kernel_cache import can_cache

ROOT = Path(__file__).resolve().parents[1]


def unusable(tmp_path: Path) -> str:
    """A directory path nobody can create (its parent is a regular file), root included."""
    blocker = tmp_path / "a-file"
    blocker.write_text("")
    return str(blocker / "coopd")


def test_unit_cache_dir_wins(tmp_path):
    assert can_cache({"NUMBA_CACHE_DIR": "/var/cache/coopd/numba"}, unusable(tmp_path))


def test_writable_source_tree_caches_in_tree(tmp_path):
    assert can_cache({"XDG_CACHE_HOME": unusable(tmp_path)}, str(tmp_path / "pkg"))
    assert (tmp_path / "pkg" / "__pycache__").is_dir()


def test_read_only_install_uses_the_users_cache_dir(tmp_path):
    assert can_cache({"XDG_CACHE_HOME": str(tmp_path / "cache")}, unusable(tmp_path))
    assert (tmp_path / "cache" / "numba").is_dir()


def test_nowhere_to_cache_compiles_in_memory(tmp_path):
    before = set(os.listdir(tmp_path.parent))
    assert not can_cache({"XDG_CACHE_HOME": unusable(tmp_path)}, unusable(tmp_path))
    assert not can_cache({"XDG_CACHE_HOME": ""}, unusable(tmp_path))  # numba would use the cwd
    assert set(os.listdir(tmp_path.parent)) == before  # no fallback directory in the temp dir


def test_importing_coopd_leaves_the_environment_alone():
    code = ("import os; before = dict(os.environ); import coopd, coopd.grid.kernels, coopd.io; "
            "print(before == dict(os.environ))")
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_CACHE_DIR"}
    env["PYTHONPATH"] = str(ROOT)
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=300)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "True"

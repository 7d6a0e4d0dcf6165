"""`python -m coopd.daemon.warmup`: what scripts/install runs once so that the daemon's first start
loads its kernels from the unit's cache directory instead of compiling them."""

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


def warmup(*args, cache_dir: Path):
    env = dict(os.environ, PYTHONPATH=str(ROOT), NUMBA_CACHE_DIR=str(cache_dir))
    return subprocess.run([sys.executable, "-m", "coopd.daemon.warmup", *args], capture_output=True,
                          text=True, env=env, timeout=900)


def test_bad_config_is_one_line_and_exit_1(tmp_path):
    bad = tmp_path / "coopd.toml"
    bad.write_text("[mapping]\nresolution = -1\n")
    r = warmup("--config", str(bad), cache_dir=tmp_path / "cache")
    assert r.returncode == 1
    assert r.stderr.startswith("coopd warm-up: configuration:") and "resolution" in r.stderr, r.stderr


@pytest.mark.slow
@pytest.mark.cpu_bound
def test_fills_the_cache_dir_the_daemon_loads_from(tmp_path):
    cache = tmp_path / "cache"
    r = warmup("--config", str(tmp_path / "absent.toml"), cache_dir=cache)  # absent: the defaults
    assert r.returncode == 0, r.stderr
    assert r.stdout.startswith("coopd warm-up: kernels compiled and cached in"), r.stdout
    cached = {p.name.split(".")[0] for p in cache.rglob("*.nbi")}
    # what the daemon's start runs before READY=1 (mapping, the map codec, the merge's first steps)
    # and what its first real merge would compile (the search, refinement and validation)
    assert {"raycast", "planes_kernels", "kernels", "preprocess", "level", "validation"} <= cached, cached
    assert {"yaw_search", "mtm", "refine"} <= cached, cached

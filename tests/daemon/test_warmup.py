"""`python -m coopd.daemon.warmup`: what scripts/install runs once so that the daemon's first start
loads its kernels from the unit's cache directory instead of compiling them."""

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


AS_ON_A_DRONE = ('import sys; sys.modules["scipy"] = None; from coopd.daemon.warmup import main; '
                 'sys.exit(main(sys.argv[1:]))')
"""`python -m coopd.daemon.warmup` where SciPy cannot be imported, as on the drone install."""


def warmup(*args, cache_dir: Path):
    env = dict(os.environ, PYTHONPATH=str(ROOT), NUMBA_CACHE_DIR=str(cache_dir))
    return subprocess.run([sys.executable, "-c", AS_ON_A_DRONE, *args], capture_output=True,
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
    """On an empty cache every kernel compiles, without SciPy: none calls LAPACK (merging/eigen.py)."""
    cache = tmp_path / "cache"
    r = warmup("--config", str(tmp_path / "absent.toml"), cache_dir=cache)  # absent: the defaults
    assert r.returncode == 0, r.stderr
    assert r.stdout.startswith("coopd warm-up: kernels compiled and cached in"), r.stdout
    cached = {p.name.split(".")[0] for p in cache.rglob("*.nbi")}
    # what the daemon's start runs before READY=1 (mapping, the map codec, the merge's first steps)
    # and what its first real merge would compile (the search, refinement and validation)
    assert {"raycast", "planes_kernels", "kernels", "preprocess", "level", "validation"} <= cached, cached
    assert {"yaw_search", "mtm", "eigen", "refine"} <= cached, cached


VALIDATING_MERGE = """
import sys
import numpy as np
from numba.core.registry import CPUDispatcher
from coopd.daemon.warmup import furnished_room, warm_up_kernels
from coopd.geometry import rigid, rotation_z
from coopd.grid import transform_grid
from coopd.mapping import MapperConfig
from coopd.merging import merge_all
from coopd.merging.hints import Hint


def signatures():
    return {f"{m.__name__}.{k}": set(v.signatures) for m in list(sys.modules.values())
            if getattr(m, "__name__", "").startswith("coopd") for k, v in vars(m).items()
            if isinstance(v, CPUDispatcher)}


warm_up_kernels(MapperConfig(), 2, merge_all)
room = furnished_room(0.1)
t1 = rigid(rotation_z(np.radians(90.0)), np.array([0.8, 0.3, 0.0]))
t2 = rigid(rotation_z(np.radians(-30.0)), np.array([-0.5, 0.2, 0.0]))
a, b = transform_grid(room, np.linalg.inv(t1)), transform_grid(room, np.linalg.inv(t2))
before = signatures()
hints = [[Hint(t1, "peer", vouched=True)], [Hint(np.linalg.inv(t1) @ t2, "peer", via=0, vouched=True)]]
r = merge_all(room, [a, b], hints=hints)
after = signatures()
assert [x.accepted for x in r.results] == [True, True] and r.vouched == 2, r
new = {k: after[k] - before.get(k, set()) for k in after}
print({k: sorted(map(str, v)) for k, v in new.items() if v})
"""


def test_a_merge_on_a_peers_result_loads_no_kernel_the_start_did_not(tmp_path):
    """Every drone but one merges by its peers' vouched edges first: the kernels of that merge are
    loaded before READY=1, not in each daemon's first merge (where loading them took 0.07 s)."""
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    r = subprocess.run([sys.executable, "-c", VALIDATING_MERGE], capture_output=True, text=True, env=env,
                       timeout=900)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "{}", r.stdout

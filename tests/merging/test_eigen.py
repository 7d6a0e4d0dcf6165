"""The Jacobi eigen-solver (Kabsch's rotation) against numpy's LAPACK, and the promise it exists for:
the merging kernels compile and run without SciPy, which the drone install leaves out."""

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from coopd.geometry import euler_to_matrix, rigid
from coopd.merging.eigen import symmetric_eigen

ROOT = Path(__file__).resolve().parents[2]


def _symmetric(n, rng, rank=None):
    a = rng.normal(size=(n, rank or n))
    return a @ a.T if rank else (a + a.T) / 2


@pytest.mark.parametrize("n, rank", [(3, None), (4, None), (16, None), (16, 15), (16, 12)])
def test_eigen_matches_lapack(n, rank):
    rng = np.random.default_rng(n * 100 + (rank or 0))
    for _ in range(20):
        a = _symmetric(n, rng, rank) * 10.0 ** rng.uniform(-3, 3)
        values, vectors = symmetric_eigen(a)
        ref = np.linalg.eigh(a)[0]
        scale = np.abs(ref).max()
        assert np.abs(values - ref).max() <= 1e-12 * scale
        assert np.abs(vectors.T @ vectors - np.eye(n)).max() <= 1e-12
        assert np.abs(a @ vectors - vectors * values).max() <= 1e-12 * scale


def test_eigen_of_repeated_values_and_diagonal_input():
    a = np.diag([2.0, 1.0, 2.0, -1.0])
    values, vectors = symmetric_eigen(a)
    assert np.allclose(values, [-1.0, 1.0, 2.0, 2.0])
    assert np.allclose(np.abs(vectors.T @ vectors), np.eye(4))
    q = rigid(euler_to_matrix(0.3, -0.2, 1.1), [0, 0, 0])[:3, :3]
    values, _ = symmetric_eigen(q @ np.diag([5.0, 5.0, 5.0]) @ q.T)
    assert np.allclose(values, 5.0)


def test_eigen_of_a_matrix_with_nan_or_inf_is_nan():
    for bad in (np.nan, np.inf):
        a = np.eye(4)
        a[1, 2] = a[2, 1] = bad
        values, vectors = symmetric_eigen(a)
        assert np.isnan(values).all() and np.isnan(vectors).all()


@pytest.mark.parametrize("scale", [1e-200, 1e-100, 1e100, 1e200])
def test_eigen_at_any_scale(scale):
    """Squares of entries this large or small would leave float range: the solver works scaled."""
    rng = np.random.default_rng(3)
    a = _symmetric(4, rng)
    values, vectors = symmetric_eigen(a * scale)
    assert np.allclose(values / scale, np.linalg.eigh(a)[0], rtol=0, atol=1e-12)
    assert np.abs(a @ vectors - vectors * (values / scale)).max() <= 1e-12


WITHOUT_SCIPY = """
import sys
sys.modules["scipy"] = None  # as on the drone install: importing SciPy fails
import numpy as np
from coopd.geometry import rigid, rotation_z
from coopd.merging.params import MergeParams
from coopd.merging.ransac import filter_correspondences
rng = np.random.default_rng(0)
pb = rng.uniform(-8, 8, (40, 3))
t = rigid(rotation_z(0.7), [2.0, -1.0, 0.3])
pa = pb @ t[:3, :3].T + t[:3, 3]
for model in ("homography", "rigid", "yaw"):
    p = MergeParams(ransac_model=model, ransac_iterations=200, hypotheses=1, gravity_aligned=model == "yaw")
    best = filter_correspondences(pb, pa, 0.1, p)[0]
    assert np.abs(best.transform - t).max() < 1e-6, (model, best.transform)
print("ok")
"""


@pytest.mark.slow
@pytest.mark.cpu_bound
def test_ransac_and_kabsch_compile_and_run_without_scipy(tmp_path):
    """A fresh kernel cache, so numba compiles: with np.linalg in a kernel it would need SciPy."""
    env = dict(os.environ, PYTHONPATH=str(ROOT), NUMBA_CACHE_DIR=str(tmp_path / "cache"))
    r = subprocess.run([sys.executable, "-c", WITHOUT_SCIPY], capture_output=True, text=True, env=env,
                       timeout=900)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "ok"

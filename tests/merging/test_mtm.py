import numpy as np
import pytest

from coopd.geometry import euler_to_matrix, rigid, rotation_angle_deg, rotation_z
from coopd.merging.mtm import estimate, euler_eq33, kabsch


def test_kabsch_recovers_a_known_transform_exactly():
    rng = np.random.default_rng(0)
    t = rigid(euler_to_matrix(0.1, -0.2, 2.5), [3.0, -1.0, 0.5])
    src = rng.normal(size=(50, 3)) * 4
    dst = src @ t[:3, :3].T + t[:3, 3]
    est = estimate(src, dst, yaw_only=False)
    assert np.allclose(est, t, atol=1e-9)


def test_kabsch_fixes_reflections():
    # planar points: the SVD alone may return a reflection; the fix must give det +1
    src = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], dtype=float)
    t = rigid(rotation_z(np.pi), [1, 2, 3])
    dst = src @ t[:3, :3].T + t[:3, 3]
    est = estimate(src, dst, yaw_only=False)
    assert np.isclose(np.linalg.det(est[:3, :3]), 1.0)
    assert np.allclose(est, t, atol=1e-9)


def test_yaw_only_recovers_yaw_and_translation():
    rng = np.random.default_rng(1)
    t = rigid(rotation_z(np.radians(250)), [-4.0, 7.0, 1.2])
    src = rng.uniform(-5, 5, (20, 3))
    est = estimate(src, src @ t[:3, :3].T + t[:3, 3], yaw_only=True)
    assert np.allclose(est, t, atol=1e-9)
    assert rotation_angle_deg(est[:3, :3].T @ t[:3, :3]) < 1e-6


def test_eq33_decomposition_round_trips():
    t = rigid(euler_to_matrix(0.05, -0.03, 1.2), [1, 2, 3])
    tx, ty, tz, roll, pitch, yaw = euler_eq33(t)
    assert np.allclose([tx, ty, tz], [1, 2, 3])
    assert np.allclose([roll, pitch, yaw], [0.05, -0.03, 1.2])


def _svd_kabsch(src, dst):
    """The textbook Kabsch (SVD of the cross-covariance, reflection fix) as the reference."""
    cs, cd = src.mean(0), dst.mean(0)
    u, _, vt = np.linalg.svd((src - cs).T @ (dst - cd))
    d = np.sign(np.linalg.det(vt.T @ u.T))
    r = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
    return rigid(r, cd - r @ cs)


@pytest.mark.parametrize("seed", range(8))
def test_kabsch_equals_the_svd_form_on_noisy_points(seed):
    rng = np.random.default_rng(seed)
    t = rigid(euler_to_matrix(*rng.uniform(-np.pi, np.pi, 3)), rng.uniform(-10, 10, 3))
    n = int(rng.integers(3, 200))
    src = rng.normal(size=(n, 3)) * rng.uniform(0.1, 10, 3)
    if seed % 2:
        src[:, 2] = 0.0  # planar points: the SVD alone would offer a reflection
    dst = src @ t[:3, :3].T + t[:3, 3] + rng.normal(0, 0.05, (n, 3))
    est, ref = kabsch(src, dst), _svd_kabsch(src, dst)
    assert np.abs(est - ref).max() < 1e-9
    assert np.isclose(np.linalg.det(est[:3, :3]), 1.0)


def test_kabsch_of_points_that_say_nothing_about_rotation_does_not_turn():
    """All points equal: no cross-covariance, so no rotation is preferred; the fit only shifts."""
    src = np.ones((5, 3))
    est = kabsch(src, src + [1.0, -2.0, 0.5])
    assert np.allclose(est, rigid(np.eye(3), [1.0, -2.0, 0.5]))

import numpy as np

from coopd.geometry import euler_to_matrix, rigid, rotation_angle_deg, rotation_z
from coopd.merging.mtm import estimate, euler_eq33


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

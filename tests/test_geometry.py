import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from coopd.geometry import (
    apply,
    check_rigid,
    euler_to_matrix,
    invert,
    matrix_to_quat,
    quat_multiply,
    quat_to_matrix,
    rigid,
    rotation_angle_deg,
    rotation_z,
)

angles = st.floats(-np.pi, np.pi, allow_nan=False)


@settings(max_examples=100, deadline=None)
@given(angles, angles, angles)
def test_quaternion_matrix_round_trip(roll, pitch, yaw):
    r = euler_to_matrix(roll, pitch, yaw)
    assert np.allclose(r @ r.T, np.eye(3), atol=1e-12) and np.isclose(np.linalg.det(r), 1.0)
    q = matrix_to_quat(r)
    assert q[0] >= 0 and np.isclose(np.linalg.norm(q), 1.0)
    assert np.allclose(quat_to_matrix(q), r, atol=1e-9)


def test_quaternion_product_composes_rotations():
    a, b = matrix_to_quat(euler_to_matrix(0.1, 0.2, 0.3)), matrix_to_quat(euler_to_matrix(-0.4, 0.5, 2.0))
    assert np.allclose(quat_to_matrix(quat_multiply(a, b)), quat_to_matrix(a) @ quat_to_matrix(b))


def test_yaw_rotates_x_to_y():
    assert np.allclose(rotation_z(np.pi / 2) @ [1, 0, 0], [0, 1, 0])
    assert np.isclose(rotation_angle_deg(rotation_z(0.5)), np.degrees(0.5))


def test_rigid_inverse_and_apply():
    t = rigid(euler_to_matrix(0.1, -0.2, 1.0), [1.0, 2.0, 3.0])
    p = np.array([[0.5, -1.0, 2.0], [0.0, 0.0, 0.0]])
    assert np.allclose(apply(invert(t), apply(t, p)), p)
    assert np.allclose(invert(t) @ t, np.eye(4))


@pytest.mark.parametrize("bad", [np.eye(3), np.diag([1, 1, -1, 1.0]), np.diag([2, 1, 1, 1.0]),
                                 np.full((4, 4), np.nan)])
def test_check_rigid_refuses(bad):
    with pytest.raises(ValueError):
        check_rigid(bad)


def test_zero_quaternion_refused():
    with pytest.raises(ValueError):
        quat_to_matrix([0, 0, 0, 0])

"""Pose buffer: bounded, ordered, linear position + slerp attitude, refusals with reasons."""

import math

import numpy as np
import pytest

from coopd.geometry import matrix_to_quat, quat_to_matrix, rotation_angle_deg, rotation_z
from coopd.vehicle.pose_buffer import PoseBuffer, PoseLookupError, PoseSample, slerp


def yaw_q(deg):
    return matrix_to_quat(rotation_z(math.radians(deg)))


def sample(t, pos=(0, 0, 0), yaw=0.0):
    return PoseSample(t, np.array(pos, float), yaw_q(yaw))


def test_slerp_endpoints_and_midpoint():
    a, b = yaw_q(0), yaw_q(90)
    assert np.allclose(slerp(a, b, 0.0), a) and np.allclose(slerp(a, b, 1.0), b)
    mid = quat_to_matrix(slerp(a, b, 0.5))
    assert rotation_angle_deg(mid.T @ rotation_z(math.radians(45))) < 1e-9
    quarter = quat_to_matrix(slerp(a, b, 0.25))
    assert rotation_angle_deg(quarter.T @ rotation_z(math.radians(22.5))) < 1e-9


def test_slerp_takes_the_short_way_when_signs_differ():
    a, b = yaw_q(170), -yaw_q(-170)  # 20 deg apart through 180; b with flipped sign
    mid = quat_to_matrix(slerp(a, b, 0.5))
    assert rotation_angle_deg(mid.T @ rotation_z(math.pi)) < 1e-9


def test_interpolates_position_linearly_and_attitude_by_slerp():
    buf = PoseBuffer()
    buf.append(sample(1.0, (0, 0, 0), 0))
    buf.append(sample(1.1, (1, 2, -1), 60))
    s = buf.at(1.075)
    assert np.allclose(s.position, [0.75, 1.5, -0.75])
    assert rotation_angle_deg(quat_to_matrix(s.quaternion).T @ rotation_z(math.radians(45))) < 1e-9
    assert buf.at(1.1).t_fc == 1.1 and buf.at(1.0).t_fc == 1.0


def test_refusals_carry_reasons():
    buf = PoseBuffer(max_gap_s=0.2)
    with pytest.raises(PoseLookupError) as e:
        buf.at(1.0)
    assert e.value.reason == "no_pose"
    for t in (1.0, 1.1, 2.0):
        buf.append(sample(t))
    for t, reason in ((0.9, "before_buffer"), (2.01, "after_buffer"), (1.5, "pose_gap")):
        with pytest.raises(PoseLookupError) as e:
            buf.at(t)
        assert e.value.reason == reason


def test_bounded_and_strictly_increasing():
    buf = PoseBuffer(capacity=10)
    for k in range(25):
        assert buf.append(sample(k * 0.01))
    assert len(buf) == 10 and buf.span() == pytest.approx((0.15, 0.24))
    assert not buf.append(sample(0.24)) and not buf.append(sample(0.1))
    buf.clear()
    assert len(buf) == 0 and buf.latest() is None

"""NED/FRD -> ENU/FLU conversions against hand-computed cases and the emulator's own conversion."""

import math

import numpy as np
import pytest

from coopd.geometry import euler_to_matrix, matrix_to_quat, quat_to_matrix
from coopd.vehicle.frames import flu_in_enu_to_frd_in_ned, frd_in_ned_to_flu_in_enu, ned_to_enu
from firmware_sim.frames import enu_flu_to_ned_frd


def axes_in_enu(q_ned_frd):
    """Body forward, left, up axes (FLU) in ENU after conversion."""
    r = quat_to_matrix(frd_in_ned_to_flu_in_enu(q_ned_frd))
    return r[:, 0], r[:, 1], r[:, 2]


def q_ned(roll_deg=0.0, pitch_deg=0.0, yaw_deg=0.0):
    return matrix_to_quat(euler_to_matrix(*np.radians([roll_deg, pitch_deg, yaw_deg])))


def test_position_swaps_north_east_and_flips_down():
    assert np.allclose(ned_to_enu([1.0, 2.0, 3.0]), [2.0, 1.0, -3.0])


def test_level_facing_north():
    fwd, left, up = axes_in_enu(q_ned())
    assert np.allclose(fwd, [0, 1, 0]) and np.allclose(left, [-1, 0, 0]) and np.allclose(up, [0, 0, 1])
    h = math.sqrt(0.5)
    assert np.allclose(frd_in_ned_to_flu_in_enu([1, 0, 0, 0]), [h, 0, 0, h])  # ENU yaw +90 deg


def test_level_facing_east_is_identity_in_enu():
    assert np.allclose(frd_in_ned_to_flu_in_enu(q_ned(yaw_deg=90)), [1, 0, 0, 0])


def test_facing_west_and_south():
    assert np.allclose(axes_in_enu(q_ned(yaw_deg=-90))[0], [-1, 0, 0])
    assert np.allclose(axes_in_enu(q_ned(yaw_deg=180))[0], [0, -1, 0])


def test_pitched_up_30_facing_north_points_nose_up():
    fwd, _, up = axes_in_enu(q_ned(pitch_deg=30))
    c, s = math.cos(math.radians(30)), math.sin(math.radians(30))
    assert np.allclose(fwd, [0, c, s]) and np.allclose(up, [0, -s, c])


def test_roll_right_facing_east_lifts_the_left_side():
    _, left, up = axes_in_enu(q_ned(roll_deg=20, yaw_deg=90))
    c, s = math.cos(math.radians(20)), math.sin(math.radians(20))
    assert np.allclose(left, [0, c, s]) and np.allclose(up, [0, -s, c])


@pytest.mark.parametrize("seed", range(5))
def test_inverse_of_the_emulators_conversion(seed):
    rng = np.random.default_rng(seed)
    q_enu = rng.normal(size=4)
    q_enu /= np.linalg.norm(q_enu)
    r_ned = enu_flu_to_ned_frd(quat_to_matrix(q_enu))  # independent implementation (firmware_sim)
    back = frd_in_ned_to_flu_in_enu(matrix_to_quat(r_ned))
    assert np.allclose(quat_to_matrix(back), quat_to_matrix(q_enu), atol=1e-12)
    assert np.allclose(quat_to_matrix(flu_in_enu_to_frd_in_ned(q_enu)), r_ned, atol=1e-12)

"""Odometry messages to map-frame poses: origin, conversion, rejections with reasons, fallback pairing."""

import math

import numpy as np
from pymavlink.dialects.v20 import common as mav

from coopd.vehicle.odometry import OdometryLimits, OdometryTracker

ENC = mav.MAVLink(None, 1, 1)
NAN21 = [math.nan] * 21


def odo(t, pos, q=(1.0, 0.0, 0.0, 0.0), frame=mav.MAV_FRAME_LOCAL_NED, quality=100, reset=0):
    return ENC.odometry_encode(
        int(t * 1e6),
        frame,
        mav.MAV_FRAME_BODY_FRD,
        *pos,
        list(q),
        0,
        0,
        0,
        0,
        0,
        0,
        NAN21,
        NAN21,
        reset,
        mav.MAV_ESTIMATOR_TYPE_VIO,
        quality,
    )


def test_first_valid_sample_is_the_origin_and_axes_are_enu():
    tr = OdometryTracker()
    assert tr.from_odometry(odo(1.0, (math.nan, 0, 0))) is None  # not valid: not the origin
    first = tr.from_odometry(odo(1.02, (10.0, 20.0, -1.0)))
    assert np.allclose(first.position, 0) and np.allclose(tr.origin_enu, [20.0, 10.0, 1.0])
    assert tr.origin_t_fc == 1.02  # when the map frame was set: the drift it inherits is the FC's then
    s = tr.from_odometry(odo(1.04, (10.5, 20.0, -1.2)))  # 0.5 m north, 0.2 m up
    assert np.allclose(s.position, [0.0, 0.5, 0.2]) and s.t_fc == 1.04
    h = math.sqrt(0.5)
    assert np.allclose(s.quaternion, [h, 0, 0, h])  # facing north = ENU yaw 90 deg


def test_rejections_are_counted_by_reason():
    tr = OdometryTracker(OdometryLimits(max_speed_m_s=10.0, jump_slack_m=0.5, accept_after_rejections=5))
    tr.from_odometry(odo(1.0, (0, 0, 0)))
    bad = [
        odo(1.1, (1e6, 0, 0)),
        odo(1.1, (0, 0, 0), q=(2.0, 0, 0, 0)),
        odo(0.9, (0, 0, 0)),
        odo(1.1, (5.0, 0, 0)),
        odo(1.1, (0, 0, 0), frame=mav.MAV_FRAME_BODY_FRD),
        odo(1.1, (0, 0, 0), quality=-1),
    ]
    assert all(tr.from_odometry(m) is None for m in bad)
    c = tr.counters
    assert (
        c["rejected_absurd"],
        c["rejected_bad_quaternion"],
        c["rejected_out_of_order"],
        c["rejected_jump"],
        c["rejected_unsupported_frame"],
        c["rejected_estimator_failed"],
    ) == (1, 1, 1, 1, 1, 1)
    assert tr.from_odometry(odo(1.2, (0.3, 0, 0))) is not None  # a plausible move is accepted


def test_a_persisting_jump_is_accepted_and_counted():
    tr = OdometryTracker(OdometryLimits(accept_after_rejections=4))
    tr.from_odometry(odo(1.0, (0, 0, 0)))
    out = [tr.from_odometry(odo(1.0 + 0.02 * k, (50.0, 0, 0))) for k in range(1, 5)]
    assert out[:3] == [None] * 3 and out[3] is not None
    assert tr.counters["jumps_accepted_persisting"] == 1


def test_estimator_reset_counter_allows_the_jump():
    tr = OdometryTracker()
    tr.from_odometry(odo(1.0, (0, 0, 0)))
    assert tr.from_odometry(odo(1.02, (40.0, 0, 0), reset=1)) is not None
    assert tr.counters["estimator_resets"] == 1


def test_fallback_pairs_local_position_with_attitude_at_the_same_time():
    tr = OdometryTracker()
    q = (math.cos(0.25), 0, 0, math.sin(0.25))
    assert tr.from_local_position(ENC.local_position_ned_encode(1000, 1, 2, -3, 0, 0, 0)) is None
    tr.on_attitude_quaternion(ENC.attitude_quaternion_encode(1000, *q, 0, 0, 0, [0, 0, 0, 0]))
    s = tr.from_local_position(ENC.local_position_ned_encode(1010, 1, 2, -3, 0, 0, 0))
    assert s is not None and np.allclose(s.position, 0) and np.allclose(tr.origin_enu, [2, 1, 3])
    assert tr.from_local_position(ENC.local_position_ned_encode(1200, 1, 2, -3, 0, 0, 0)) is None
    assert tr.counters["fallback_unpaired"] == 2

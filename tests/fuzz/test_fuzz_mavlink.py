"""Fuzz the vehicle link's receive path with random and mutated MAVLink datagrams (valid CRCs too)."""

import math

from hypothesis import given
from hypothesis import strategies as st
from pymavlink.dialects.v20 import common as mav

from tests.fuzz.ci_budget import CI_SETTINGS, assert_mutations_clean
from tests.fuzz.harness import MavlinkIngestTarget

TARGET = MavlinkIngestTarget()
FC = mav.MAVLink(None, 7, 1)
f32 = st.floats(width=32)
u64 = st.integers(0, 2**64 - 1)


def test_mutated_datagrams_keep_the_contract():
    assert_mutations_clean(TARGET, cases=3000)


@CI_SETTINGS
@given(st.binary(max_size=300))
def test_random_datagrams(data):
    TARGET.check(data)


@CI_SETTINGS
@given(u64, st.integers(0, 255), st.integers(0, 255), f32, f32, f32, st.lists(f32, min_size=4, max_size=4),
       st.lists(f32, min_size=6, max_size=6), st.integers(0, 255), st.integers(-128, 127))
def test_odometry_with_arbitrary_field_values(t_us, frame, child, x, y, z, q, rates, reset, quality):
    nan21 = [math.nan] * 21
    msg = FC.odometry_encode(t_us, frame, child, x, y, z, q, *rates, nan21, nan21, reset, 0, quality)
    TARGET.check(msg.pack(FC))


@CI_SETTINGS
@given(st.integers(0, 2**32 - 1), f32, f32, f32, f32, f32, f32, st.lists(f32, min_size=4, max_size=4),
       st.integers(-(2**63), 2**63 - 1), st.integers(-(2**63), 2**63 - 1), u64)
def test_fallback_pose_attitude_and_clock_messages(t_ms, x, y, z, vx, vy, vz, q, tc1, ts1, unix_us):
    TARGET.check(FC.attitude_quaternion_encode(t_ms, *q, vx, vy, vz, [0, 0, 0, 0]).pack(FC))
    TARGET.check(FC.local_position_ned_encode(t_ms, x, y, z, vx, vy, vz).pack(FC))
    TARGET.check(FC.timesync_encode(tc1, ts1).pack(FC))
    TARGET.check(FC.system_time_encode(unix_us, t_ms).pack(FC))

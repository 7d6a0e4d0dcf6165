"""The map frame across FC reboots and estimator resets: the continuity rule, the pause, re-anchoring."""

import math

import numpy as np
import pytest
from test_link_parsing import Recorder, heartbeat, odometry

from coopd.geometry import matrix_to_quat, rotation_z
from coopd.vehicle import LinkConfig, VehicleLink
from coopd.vehicle.frame_continuity import (
    FC_REBOOT,
    ContinuityLimits,
    FrameContinuity,
    corrected,
    hold_guess,
    judge_break,
    yaw_of_quaternion,
)
from coopd.vehicle.pose_buffer import PoseLookupError, PoseSample


def pose(t, xyz, yaw_deg=0.0):
    return PoseSample(t, np.array(xyz, dtype=float), matrix_to_quat(rotation_z(math.radians(yaw_deg))))


def test_a_pose_that_continues_within_the_gap_allowance_is_continuous():
    before = pose(10.0, (4.0, 2.0, 1.5), 30.0)
    limits = ContinuityLimits(slack_m=0.3, max_speed_m_s=0.5, max_turn_deg=5.0, max_turn_rate_deg_s=10.0)
    v = judge_break(before, pose(0.1, (4.5, 2.2, 1.5), 36.0), 2.0, FC_REBOOT, limits)
    assert v.continuous and v.allowed_m == pytest.approx(1.3) and v.allowed_deg == pytest.approx(25.0)
    moved = judge_break(before, pose(0.1, (1.0, -0.5, 1.2), 30.0), 2.0, FC_REBOOT, limits)
    assert not moved.continuous
    assert moved.reason == "fc frame moved 3.9 m and turned 0 deg after an FC reboot"
    assert "3.92 m" in moved.detail and "2.0 s gap" in moved.detail
    turned = judge_break(before, pose(10.03, (4.0, 2.0, 1.5), -150.0), 0.03, FC_REBOOT, limits)
    assert not turned.continuous and turned.turn_deg == pytest.approx(180.0)


def test_the_hold_guess_carries_the_first_new_pose_onto_the_last_old_one():
    before, after = pose(10.0, (4.0, 2.0, 1.5), 30.0), pose(0.1, (0.1, -0.2, 0.0), 100.0)
    guess = hold_guess(before, after)
    moved = corrected(after, guess)
    assert np.allclose(moved.position, before.position)
    assert math.degrees(yaw_of_quaternion(moved.quaternion)) == pytest.approx(30.0)


def test_a_moved_frame_pauses_until_reanchored_and_an_old_anchor_is_refused():
    fc = FrameContinuity()
    assert np.allclose(fc.admit(pose(9.9, (4.0, 2.0, 1.5)), 100.0).position, (4.0, 2.0, 1.5))
    fc.on_break(FC_REBOOT, pose(9.9, (4.0, 2.0, 1.5)), 100.0)
    assert fc.admit(pose(0.5, (0.0, 0.0, 0.0)), 102.0) is None
    assert fc.paused.startswith("fc frame moved 4.7 m") and fc.note() == "map paused: FC frame moved 4.7 m"
    assert fc.admit(pose(0.6, (0.05, 0.0, 0.0)), 102.1) is None
    assert np.allclose(fc.raw_pose_at(0.55).position, (0.025, 0, 0))
    epoch, guess = fc.pending_anchor()
    assert np.allclose(guess[:3, 3], (4.0, 2.0, 1.5))
    assert not fc.reanchor(epoch - 1, guess, "test") and fc.paused is not None
    fc.refuse("too little overlap")
    assert fc.paused.endswith("re-anchoring: too little overlap")
    assert fc.reanchor(epoch, guess, "test") and fc.paused is None and fc.note() is None
    assert np.allclose(fc.admit(pose(0.7, (1.0, 0.0, 0.0)), 102.2).position, (5.0, 2.0, 1.5))
    with pytest.raises(PoseLookupError):
        fc.raw_pose_at(0.55)  # the raw buffer went with the pause
    s = fc.status()
    assert s["counters"] == {"breaks": 1, "breaks_paused": 1, "anchors": 1, "anchors_stale": 1,
                             "anchors_refused": 1}
    assert s["last_anchor"]["shift_m"] == [4.0, 2.0, 1.5]


def test_a_continuing_frame_keeps_mapping_and_the_correction():
    fc = FrameContinuity()
    fc.correction = np.eye(4)
    fc.correction[:3, 3] = (1.0, 0.0, 0.0)
    fc.on_break(FC_REBOOT, pose(9.9, (5.0, 2.0, 1.5)), 100.0)
    out = fc.admit(pose(0.5, (4.1, 2.0, 1.5)), 101.0)  # 0.1 m from the last map pose after correction
    assert out is not None and np.allclose(out.position, (5.1, 2.0, 1.5)) and fc.paused is None
    assert fc.status()["last_break"]["continuous"]


def test_the_link_pauses_on_an_estimator_reset_and_on_a_reboot_with_a_moved_frame():
    link = VehicleLink(LinkConfig(connection="udpin:127.0.0.1:1"), transport=Recorder())
    now = 50.0
    link._ingest(heartbeat(), now)
    for k in range(10):
        link._ingest(odometry(5.0 + 0.03 * k, 0.0), now + 0.03 * k)
    assert link.pose_at(5.1).position[1] == pytest.approx(0.0)
    link._ingest(odometry(5.4, 6.0, reset=1), now + 0.4)  # the reported pose jumps 6 m north
    assert link.frames.paused.endswith("after an estimator reset")
    assert link.odometry.counters["estimator_resets"] == 1
    with pytest.raises(PoseLookupError) as e:
        link.pose_at(5.4)
    assert e.value.reason == "frame_paused"
    assert link.pose_at(5.2).position[1] == pytest.approx(0.0), "frames from before the reset still map"
    link._update_state(now + 0.45)
    assert not link.odometry_stale(now + 0.45), "odometry flows; mapping pauses for the frame, not the link"
    epoch, guess = link.frames.pending_anchor()
    link.frames.reanchor(epoch, guess, "test")
    link._ingest(odometry(5.5, 6.1, reset=1), now + 0.5)
    assert link.pose_at(5.5).position[1] == pytest.approx(0.1, abs=1e-6)
    # A reboot whose estimator kept its frame: mapping continues without a pause.
    link._ingest(odometry(0.2, 6.1), now + 2.5)
    assert link.counters["fc_reboots"] == 1 and link.frames.paused is None
    assert link.poses.latest().position[1] == pytest.approx(0.1, abs=1e-6), "the correction carries on"

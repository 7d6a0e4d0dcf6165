"""Pose-frame association: interpolated body pose + mount -> camera pose; skips counted by reason."""

import math
import threading
import time
from dataclasses import dataclass

import numpy as np
import pytest

from coopd.geometry import matrix_to_quat, quat_to_matrix, rotation_z
from coopd.mapping import CameraMount, Intrinsics
from coopd.mapping.association import FrameAssociator
from coopd.vehicle.pose_buffer import PoseBuffer, PoseSample

INTR = Intrinsics.from_fov(8, 6, 87.0)


@dataclass
class Frame:
    seq: int
    t_fc: float
    depth: np.ndarray = None
    intrinsics: Intrinsics = INTR


class FakeLink:
    """The two methods association uses, over a real PoseBuffer."""

    def __init__(self):
        self.poses = PoseBuffer(max_gap_s=0.2)
        self.stale = False

    def pose_at(self, t):
        return self.poses.at(t)

    def odometry_stale(self):
        return self.stale

    def add(self, t, pos, yaw_deg):
        self.poses.append(
            PoseSample(t, np.array(pos, float), matrix_to_quat(rotation_z(math.radians(yaw_deg))))
        )


@pytest.fixture
def link():
    lk = FakeLink()
    lk.add(10.0, (0, 0, 1), 80)
    lk.add(10.1, (1, 0, 1), 100)
    return lk


def test_camera_pose_is_the_mount_on_the_interpolated_body(link):
    a = FrameAssociator(link).associate(Frame(1, 10.05))
    assert np.allclose(a.body_pose.position, [0.5, 0, 1]) and a.stamp == 10.05
    r = quat_to_matrix(a.camera_pose.quaternion)
    # Body faces +y (yaw 90 deg): optical z (forward) = +y, optical x (right) = +x, optical y (down) = -z.
    assert np.allclose(r[:, 2], [0, 1, 0], atol=1e-9) and np.allclose(r[:, 0], [1, 0, 0], atol=1e-9)
    assert np.allclose(r[:, 1], [0, 0, -1], atol=1e-9)


def test_mount_offset_and_tilt_are_applied(link):
    mount = CameraMount(translation=np.array([0.1, 0.0, -0.05])).tilted(30.0)
    a = FrameAssociator(link, mount).associate(Frame(1, 10.05))
    assert np.allclose(a.camera_pose.position, [0.5, 0.1, 0.95])
    fwd = quat_to_matrix(a.camera_pose.quaternion)[:, 2]
    assert np.allclose(fwd, [0, math.cos(math.radians(30)), -math.sin(math.radians(30))], atol=1e-9)


def test_skips_are_counted_by_reason(link):
    link.add(10.5, (1, 0, 1), 100)  # 0.4 s after the previous pose: a gap
    assoc = FrameAssociator(link, max_wait_s=0.0)
    for t in (9.0, 10.3, 11.0):
        assert assoc.associate(Frame(0, t)) is None
    assert assoc.skipped == {"before_buffer": 1, "pose_gap": 1, "after_buffer": 1}


def test_stale_odometry_pauses_and_resumes(link):
    assoc = FrameAssociator(link)
    link.stale = True
    assert assoc.associate(Frame(1, 10.05)) is None and assoc.status()["paused"]
    link.stale = False
    assert assoc.associate(Frame(2, 10.06)) is not None and not assoc.status()["paused"]
    assert assoc.skipped["odometry_stale"] == 1 and assoc.associated == 1


def test_a_frame_slightly_ahead_of_odometry_waits_for_it(link):
    assoc = FrameAssociator(link, max_wait_s=0.5)
    timer = threading.Timer(0.05, lambda: link.add(10.2, (2, 0, 1), 100))
    timer.start()
    t0 = time.monotonic()
    a = assoc.associate(Frame(3, 10.15))
    timer.join()
    assert a is not None and np.allclose(a.body_pose.position, [1.5, 0, 1]) and time.monotonic() - t0 < 0.45


def test_waiting_is_bounded(link):
    assoc = FrameAssociator(link, max_wait_s=0.1)
    t0 = time.monotonic()
    assert assoc.associate(Frame(4, 10.3)) is None
    assert 0.1 <= time.monotonic() - t0 < 0.6 and assoc.skipped["after_buffer"] == 1

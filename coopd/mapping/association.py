"""Pose-frame association: each depth frame gets the body pose interpolated at its FC timestamp."""

from __future__ import annotations

import logging
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from .sensor import CameraMount, FrameRejected, Intrinsics, Pose

log = logging.getLogger("coopd.mapping")


class PoseSource(Protocol):
    """What association needs from the vehicle link (coopd.vehicle.VehicleLink provides it)."""

    def pose_at(self, t_fc: float):
        """Body pose (attributes position, quaternion) at FC time; raises LookupError with `.reason`."""

    def odometry_stale(self) -> bool:
        """True while odometry is not arriving (link lost, estimator silent)."""


class TimedDepth(Protocol):
    """What association needs from a frame (coopd.camera.DepthFrame provides it)."""

    seq: int
    t_fc: float
    depth: np.ndarray
    intrinsics: Intrinsics


@dataclass(frozen=True)
class AssociatedFrame:
    """A frame ready for Mapper.integrate(depth, intrinsics, camera_pose, stamp)."""

    seq: int
    stamp: float  # FC time, seconds
    depth: np.ndarray
    intrinsics: Intrinsics
    body_pose: Pose
    camera_pose: Pose


def pose_waiting(pose_at: Callable[[float], object], t_fc: float, max_wait_s: float, poll_s: float = 0.005,
                 stale: Callable[[], bool] = lambda: False):
    """pose_at(t_fc), waiting up to max_wait_s while the frame is newer than the newest pose: odometry
    for a frame's time may arrive just after the frame. Raises pose_at's LookupError (with `.reason`)."""
    deadline = time.monotonic() + max_wait_s
    while True:
        try:
            return pose_at(t_fc)
        except LookupError as e:
            if getattr(e, "reason", None) != "after_buffer" or time.monotonic() >= deadline or stale():
                raise
            time.sleep(poll_s)


class FrameAssociator:
    """Frame time -> interpolated body pose (+ camera mount) -> camera pose; skips are counted by reason."""

    def __init__(
        self,
        poses: PoseSource,
        mount: CameraMount | None = None,
        max_wait_s: float = 0.1,
        poll_s: float = 0.005,
    ):
        if not (0 <= max_wait_s <= 1.0):
            raise ValueError("max_wait_s must be within 0..1 s")
        self.poses = poses
        self.mount = mount if mount is not None else CameraMount()
        self.max_wait_s = max_wait_s
        self.poll_s = poll_s
        self.skipped: Counter = Counter()
        self.associated = 0
        self.last_skip: str | None = None
        """Why the last frame was skipped (frame_paused: the FC's frame is not anchored, see reanchor)."""
        self._paused = False

    def associate(self, frame: TimedDepth) -> AssociatedFrame | None:
        """The frame with its camera pose, or None (counted) when no trustworthy pose exists.

        A frame newer than the newest pose waits up to max_wait_s for odometry to catch up.
        """
        if self.poses.odometry_stale():
            return self._skip("odometry_stale")
        self._set_paused(False)
        try:
            sample = pose_waiting(self.poses.pose_at, frame.t_fc, self.max_wait_s, self.poll_s,
                                  self.poses.odometry_stale)
        except LookupError as e:
            return self._skip(getattr(e, "reason", "no_pose"))
        try:
            body = Pose(sample.position, sample.quaternion)
            camera = self.mount.camera_pose(body)
        except (FrameRejected, ValueError):
            return self._skip("bad_pose")
        self.associated += 1
        return AssociatedFrame(frame.seq, frame.t_fc, frame.depth, frame.intrinsics, body, camera)

    def _skip(self, reason: str) -> None:
        self.skipped[reason] += 1
        self.last_skip = reason
        if reason == "odometry_stale":
            self._set_paused(True)
        return None

    def _set_paused(self, paused: bool) -> None:
        """Log each transition once: operators see mapping pause and resume, not every frame."""
        if paused != self._paused:
            self._paused = paused
            if paused:
                log.warning(
                    "mapping paused: odometry stale (%d frames skipped so far)", sum(self.skipped.values())
                )
            else:
                log.info(
                    "mapping resumed: odometry fresh again (%d frames skipped while paused)",
                    self.skipped["odometry_stale"],
                )

    def status(self) -> dict:
        return {"associated": self.associated, "paused": self._paused, "skipped": dict(self.skipped)}

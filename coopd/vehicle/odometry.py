"""FC odometry messages to validated body poses in the map frame (origin: the first valid sample)."""

from __future__ import annotations

import logging
import math
from collections import Counter
from dataclasses import dataclass

import numpy as np

from .frames import frd_in_ned_to_flu_in_enu, ned_to_enu
from .pose_buffer import PoseSample, slerp

log = logging.getLogger("coopd.vehicle")

MAV_FRAME_LOCAL_NED = 1
MAV_FRAME_LOCAL_FRD = 20
MAV_FRAME_BODY_FRD = 12
MAV_FRAME_BODY_NED = 8  # what PX4 <= 1.12 put in child_frame_id for "the body frame"
BODY_FRAMES = (MAV_FRAME_BODY_FRD, MAV_FRAME_BODY_NED, 0)
NED_LIKE_FRAMES = (MAV_FRAME_LOCAL_NED, MAV_FRAME_LOCAL_FRD)
ATTITUDE_PAIRING_S = 0.05


@dataclass(frozen=True)
class OdometryLimits:
    """What a plausible pose looks like; anything else is rejected and counted."""

    max_abs_position_m: float = 10_000.0
    max_speed_m_s: float = 30.0
    jump_slack_m: float = 0.5
    quaternion_norm_tolerance: float = 0.1
    accept_after_rejections: int = 30  # a jump that persists this many samples is a new truth (counted)


class OdometryTracker:
    """Turns ODOMETRY (or LOCAL_POSITION_NED + ATTITUDE_QUATERNION) into map-frame PoseSamples.

    The map frame is the FC's local frame converted to ENU-like axes (x, y horizontal, z up) and
    translated so the first valid sample's position is the origin; yaw is kept, so the map stays
    gravity-aligned and shares the FC's heading reference.
    """

    def __init__(self, limits: OdometryLimits = OdometryLimits()):
        self.limits = limits
        self.origin_enu: np.ndarray | None = None
        self.origin_t_fc: float | None = None
        """FC time of the sample that set the origin (None when the origin was restored from disk)."""
        self.counters: Counter = Counter()
        self._last: PoseSample | None = None
        self._rejected_in_row = 0
        self._attitude: tuple[tuple[float, np.ndarray], ...] | None = None
        self._reset_counter: int | None = None
        self._reset_seen = False

    # -- message entry points -------------------------------------------------------------------

    def from_odometry(self, m) -> PoseSample | None:
        """An ODOMETRY message (pose in frame_id, attitude of child_frame_id) to a sample, or None."""
        if m.frame_id not in NED_LIKE_FRAMES or m.child_frame_id not in BODY_FRAMES:
            return self._reject("unsupported_frame")
        if getattr(m, "quality", 0) < 0:
            return self._reject("estimator_failed")
        reset = int(getattr(m, "reset_counter", 0))
        if self._reset_counter is not None and reset != self._reset_counter:
            self.counters["estimator_resets"] += 1
            log.warning(
                "estimator reset (counter %d -> %d): accepting the next pose jump", self._reset_counter, reset
            )
            self._last = None
            self._reset_seen = True
        self._reset_counter = reset
        return self._accept(m.time_usec * 1e-6, (m.x, m.y, m.z), m.q)

    def on_attitude_quaternion(self, m) -> None:
        """Remember the last two ATTITUDE_QUATERNIONs for the LOCAL_POSITION_NED fallback."""
        sample = (m.time_boot_ms * 1e-3, np.array([m.q1, m.q2, m.q3, m.q4], dtype=np.float64))
        if self._attitude is not None and sample[0] <= self._attitude[-1][0]:
            self._attitude = (sample,)        # time went back (or repeated): start over
        else:
            self._attitude = ((self._attitude or ())[-1:]) + (sample,)

    def from_local_position(self, m) -> PoseSample | None:
        """LOCAL_POSITION_NED with the attitude at its timestamp: slerp between the last two
        ATTITUDE_QUATERNIONs, carried on at the same rate for a position up to one attitude period
        newer (the streams are not in step; the latest attitude alone lags by up to a period)."""
        t = m.time_boot_ms * 1e-3
        if self._attitude is None or abs(self._attitude[-1][0] - t) > ATTITUDE_PAIRING_S:
            self.counters["fallback_unpaired"] += 1
            return None
        q = self._attitude[-1][1]
        if len(self._attitude) == 2:
            (t0, q0), (t1, q1) = self._attitude
            if t1 - t0 <= 2 * ATTITUDE_PAIRING_S:
                q = slerp(q0, q1, min(max((t - t0) / (t1 - t0), 0.0), 2.0))
        return self._accept(t, (m.x, m.y, m.z), q)

    def take_reset(self) -> bool:
        """True once after the estimator reported a reset (ODOMETRY.reset_counter changed)."""
        seen, self._reset_seen = self._reset_seen, False
        return seen

    def restart_time_base(self) -> None:
        """The FC rebooted: forget the previous sample so its timestamps don't reject new ones."""
        self._last = None
        self._attitude = None
        self._reset_counter = None

    # -- validation -----------------------------------------------------------------------------

    def _reject(self, reason: str) -> None:
        self.counters["rejected_" + reason] += 1
        self._rejected_in_row += 1
        return None

    def _accept(self, t_fc: float, p_ned, q_ned_frd) -> PoseSample | None:
        lim = self.limits
        p = np.array(p_ned, dtype=np.float64)
        q = np.array(q_ned_frd, dtype=np.float64).reshape(-1)
        if q.shape != (4,) or not (np.all(np.isfinite(p)) and np.all(np.isfinite(q)) and math.isfinite(t_fc)):
            return self._reject("not_finite")
        if np.abs(p).max() > lim.max_abs_position_m or t_fc <= 0:
            return self._reject("absurd")
        if abs(float(np.linalg.norm(q)) - 1.0) > lim.quaternion_norm_tolerance:
            return self._reject("bad_quaternion")
        p_enu = ned_to_enu(p)
        q_enu = frd_in_ned_to_flu_in_enu(q)
        last = self._last
        if last is not None:
            dt = t_fc - last.t_fc
            if dt <= 0:
                return self._reject("out_of_order")
            jump = float(np.linalg.norm(p_enu - last.position))
            if jump > lim.max_speed_m_s * dt + lim.jump_slack_m:
                if self._rejected_in_row + 1 < lim.accept_after_rejections:
                    return self._reject("jump")
                self.counters["jumps_accepted_persisting"] += 1
                log.warning(
                    "odometry jumped %.2f m and stayed there for %d samples: accepted",
                    jump,
                    self._rejected_in_row + 1,
                )
        if self.origin_enu is None:
            self.origin_enu = p_enu.copy()
            self.origin_t_fc = t_fc
            log.info(
                "map origin set at the first valid odometry sample: FC local ENU (%.3f, %.3f, %.3f) m, "
                "t_fc=%.3f s",
                *p_enu,
                t_fc,
            )
        self._rejected_in_row = 0
        sample = PoseSample(t_fc, p_enu, q_enu)
        self._last = sample
        self.counters["accepted"] += 1
        return PoseSample(t_fc, p_enu - self.origin_enu, q_enu)

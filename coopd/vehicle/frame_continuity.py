"""The map frame across FC reboots and estimator resets.

coopd's map frame is the FC's local frame as it was when mapping started. When the FC reboots or its
estimator resets its position (ODOMETRY.reset_counter changes), the estimator may come back with its
local origin (and heading) elsewhere: every later pose is then offset, and fusing frames with those
poses would draw a second, shifted copy of every wall. FrameContinuity owns the correction carrying
the FC's current frame into the map frame: after such a break it compares the first new pose with the
last one before (judge_break); if they continue each other the correction stays and mapping goes on,
otherwise mapping pauses with a reason until the new frame is re-anchored onto the map
(coopd.mapping.reanchor registers a short local map against the own map and calls reanchor()).
"""

from __future__ import annotations

import logging
import math
import threading
from collections import Counter
from dataclasses import dataclass

import numpy as np

from ..geometry import matrix_to_quat, quat_multiply, rotation_z
from .pose_buffer import PoseBuffer, PoseLookupError, PoseSample

log = logging.getLogger("coopd.vehicle")

FC_REBOOT = "an FC reboot"
ESTIMATOR_RESET = "an estimator reset"


@dataclass(frozen=True)
class ContinuityLimits:
    """How far the vehicle may have moved and turned across a break for the new frame to count as the
    old one continued (a hovering vehicle: slack plus a slow drift over the gap)."""

    slack_m: float = 0.3
    max_speed_m_s: float = 0.5
    max_turn_deg: float = 5.0
    max_turn_rate_deg_s: float = 10.0

    def __post_init__(self):
        if not (0 <= self.slack_m <= 10 and 0 <= self.max_speed_m_s <= 30):
            raise ValueError("slack_m within 0..10 m, max_speed_m_s within 0..30 m/s")
        if not (0 <= self.max_turn_deg <= 180 and 0 <= self.max_turn_rate_deg_s <= 360):
            raise ValueError("max_turn_deg within 0..180, max_turn_rate_deg_s within 0..360")


@dataclass(frozen=True)
class BreakVerdict:
    """What judge_break found: the jump across the break and whether the frames continue each other."""

    cause: str
    jump_m: float
    turn_deg: float
    gap_s: float
    allowed_m: float
    allowed_deg: float

    @property
    def continuous(self) -> bool:
        return self.jump_m <= self.allowed_m and self.turn_deg <= self.allowed_deg

    @property
    def reason(self) -> str:
        """Why mapping paused, for operators (status field)."""
        return f"fc frame moved {self.jump_m:.1f} m and turned {self.turn_deg:.0f} deg after {self.cause}"

    @property
    def note(self) -> str:
        """The pause in a few words (a STATUSTEXT to the GCS, at most 50 bytes with its prefix)."""
        return f"map paused: FC frame moved {min(self.jump_m, 9999.0):.1f} m"

    @property
    def detail(self) -> str:
        """The numbers behind the verdict (log line)."""
        return (f"{self.jump_m:.2f} m, {self.turn_deg:.1f} deg over a {self.gap_s:.1f} s gap; at most "
                f"{self.allowed_m:.2f} m, {self.allowed_deg:.1f} deg expected")


def yaw_of_quaternion(q) -> float:
    """Heading (rad) of a body quaternion (w, x, y, z) in an ENU-like frame."""
    w, x, y, z = (float(v) for v in q)
    return math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))


def wrap_deg(a: float) -> float:
    """An angle in degrees wrapped into [-180, 180)."""
    return (a + 180.0) % 360.0 - 180.0


def judge_break(before: PoseSample, after: PoseSample, gap_s: float, cause: str,
                limits: ContinuityLimits = ContinuityLimits()) -> BreakVerdict:
    """Compare the first pose after a break with the last one before (both in the map frame by the
    correction in force): they continue each other if the position moved at most slack + speed x gap
    and the heading turned at most max_turn + rate x gap."""
    gap = max(0.0, float(gap_s))
    jump = float(np.linalg.norm(np.asarray(after.position) - np.asarray(before.position)))
    turned = yaw_of_quaternion(after.quaternion) - yaw_of_quaternion(before.quaternion)
    turn = abs(wrap_deg(math.degrees(turned)))
    return BreakVerdict(cause, jump, turn, gap, limits.slack_m + limits.max_speed_m_s * gap,
                        limits.max_turn_deg + limits.max_turn_rate_deg_s * gap)


def hold_guess(before: PoseSample, after: PoseSample) -> np.ndarray:
    """The 4x4 (a turn about z and a shift) carrying the new frame's first pose onto the old frame's last
    one: the right correction if the vehicle held its position and heading across the break."""
    turn = yaw_of_quaternion(before.quaternion) - yaw_of_quaternion(after.quaternion)
    out = np.eye(4)
    out[:3, :3] = rotation_z(turn)
    out[:3, 3] = np.asarray(before.position) - out[:3, :3] @ np.asarray(after.position)
    return out


def corrected(sample: PoseSample, correction: np.ndarray) -> PoseSample:
    """A pose of the FC's current frame carried into the map frame."""
    rot = correction[:3, :3]
    q = quat_multiply(matrix_to_quat(rot), sample.quaternion)
    return PoseSample(sample.t_fc, rot @ sample.position + correction[:3, 3], q / np.linalg.norm(q))


class FrameContinuity:
    """Owns the correction from the FC's current frame to the map frame, and the pause while it is
    unknown. The link thread calls on_break() and admit(); the mapping side reads pending_anchor() and
    raw_pose_at() and calls reanchor(); status() from anywhere (thread-safe)."""

    def __init__(self, limits: ContinuityLimits = ContinuityLimits(), raw_capacity: int = 1200,
                 raw_max_gap_s: float = 0.25):
        self.limits = limits
        self.correction = np.eye(4)
        self.paused: str | None = None
        """Why mapping is paused (the new frame is not anchored on the map), or None."""
        self.epoch = 0
        """Counts breaks; a re-anchoring found for an older epoch is refused."""
        self.counters: Counter = Counter()
        self.last_verdict: BreakVerdict | None = None
        self.last_anchor: dict | None = None
        self._raw = PoseBuffer(raw_capacity, raw_max_gap_s)
        self._before: tuple[PoseSample, float] | None = None
        """The last map-frame pose before the break and when it arrived (host time)."""
        self._first_after: PoseSample | None = None
        self._pending: str | None = None
        """The cause of a break whose first new pose has not arrived yet."""
        self._lock = threading.Lock()

    def on_break(self, cause: str, last: PoseSample | None, last_host_s: float) -> None:
        """The FC rebooted or its estimator reset; `last`: the newest map-frame pose before it (None if
        none: nothing to compare, the map frame starts with the new one)."""
        with self._lock:
            self.epoch += 1
            self.counters["breaks"] += 1
            self._raw.clear()
            self._first_after = None
            if self.paused is None:  # while paused, the pose before the first break stays the anchor
                self._before = None if last is None else (last, last_host_s)
            if self._before is not None:
                self._pending = cause

    def admit(self, raw: PoseSample, now: float) -> PoseSample | None:
        """A pose of the FC's current frame: returned in the map frame, or None (buffered for the
        re-anchoring) while mapping is paused."""
        with self._lock:
            if self._pending is not None:
                self._judge(raw, now)
            if self.paused is None:
                return corrected(raw, self.correction)
            if self._first_after is None:
                self._first_after = raw
            if not self._raw.append(raw):
                self.counters["raw_out_of_order"] += 1
            return None

    def _judge(self, raw: PoseSample, now: float) -> None:
        cause, self._pending = self._pending, None
        before, before_s = self._before
        verdict = judge_break(before, corrected(raw, self.correction), now - before_s, cause, self.limits)
        self.last_verdict = verdict
        if verdict.continuous:
            self.counters["breaks_continuous"] += 1
            self.paused = None
            log.info("map frame kept after %s: the new FC frame continues the old one (%s)", cause,
                     verdict.detail)
            return
        self.counters["breaks_paused"] += 1
        self.paused = verdict.reason
        log.warning("mapping paused: FC frame moved after %s (%s); re-anchoring the new frame on the map",
                    cause, verdict.detail)

    def pending_anchor(self) -> tuple[int, np.ndarray] | None:
        """(epoch, hold-position guess of the correction) while paused with new poses to anchor."""
        with self._lock:
            if self.paused is None or self._before is None or self._first_after is None:
                return None
            guess = hold_guess(self._before[0], self._first_after)
            return self.epoch, guess

    def newest_raw_t_fc(self) -> float | None:
        """FC time of the newest pose of the unanchored frame (it has passed), or None."""
        span = self._raw.span()
        return None if span is None else span[1]

    def raw_pose_at(self, t_fc: float) -> PoseSample:
        """A pose of the FC's current (not yet anchored) frame; raises PoseLookupError."""
        return self._raw.at(t_fc)

    def reanchor(self, epoch: int, correction: np.ndarray, detail: str) -> bool:
        """Set the correction found for break `epoch` and resume mapping; False if another break came."""
        with self._lock:
            if epoch != self.epoch or self.paused is None:
                self.counters["anchors_stale"] += 1
                return False
            old = self.paused
            self.correction = np.array(correction, dtype=np.float64)
            self.paused = None
            self._raw.clear()
            self._first_after = None
            self.counters["anchors"] += 1
            turn = math.degrees(math.atan2(self.correction[1, 0], self.correction[0, 0]))
            self.last_anchor = {"shift_m": [round(float(v), 3) for v in self.correction[:3, 3]],
                                "turn_deg": round(turn, 2), "detail": detail}
        log.info("mapping resumed: new FC frame re-anchored on the map, shift (%.2f, %.2f, %.2f) m, turn "
                 "%.1f deg (%s); it was paused because %s", *self.correction[:3, 3], turn, detail, old)
        return True

    def refuse(self, why: str) -> None:
        """The re-anchoring failed for now: the pause reason says so (status, GCS)."""
        with self._lock:
            if self.paused is not None and self.last_verdict is not None:
                self.paused = f"{self.last_verdict.reason}; re-anchoring: {why}"
                self.counters["anchors_refused"] += 1

    def note(self) -> str | None:
        """The pause in a few words for the GCS, or None while mapping in an anchored frame."""
        with self._lock:
            if self.paused is None:
                return None
            verdict = self.last_verdict
            return "map paused: FC frame not anchored" if verdict is None else verdict.note

    def lookup_error(self) -> PoseLookupError:
        """What pose_at raises while paused."""
        return PoseLookupError("frame_paused", self.paused or "map frame not anchored")

    def status(self) -> dict:
        with self._lock:
            v = self.last_verdict
            return {
                "paused": self.paused,
                "epoch": self.epoch,
                "correction": {"shift_m": [round(float(v), 3) for v in self.correction[:3, 3]],
                               "turn_deg": round(math.degrees(math.atan2(self.correction[1, 0],
                                                                         self.correction[0, 0])), 2)},
                "last_break": None if v is None else {
                    "cause": v.cause, "jump_m": round(v.jump_m, 3), "turn_deg": round(v.turn_deg, 2),
                    "gap_s": round(v.gap_s, 2), "continuous": v.continuous},
                "last_anchor": self.last_anchor,
                "counters": dict(self.counters),
            }


__all__ = ["BreakVerdict", "ContinuityLimits", "FrameContinuity", "corrected", "hold_guess", "judge_break"]

"""Bounded, time-ordered buffer of body poses in the map frame, interpolated at any time inside it."""

import bisect
import threading
from collections import deque
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class PoseSample:
    """Body (FLU) pose in the map frame at a flight-controller time (seconds since FC boot)."""

    t_fc: float
    position: np.ndarray
    quaternion: np.ndarray  # (w, x, y, z), unit


class PoseLookupError(LookupError):
    """No pose can be given for the requested time; `reason` is a short counter key."""

    def __init__(self, reason: str, detail: str):
        super().__init__(f"{reason}: {detail}")
        self.reason = reason


def slerp(q0, q1, u: float) -> np.ndarray:
    """Spherical linear interpolation of unit quaternions (w, x, y, z) along the shorter arc."""
    q0 = np.asarray(q0, dtype=np.float64)
    q1 = np.asarray(q1, dtype=np.float64)
    d = float(np.dot(q0, q1))
    if d < 0.0:
        q1, d = -q1, -d
    if d > 0.9995:  # nearly parallel: normalised lerp is exact to float precision
        q = q0 + u * (q1 - q0)
        return q / np.linalg.norm(q)
    theta = np.arccos(min(d, 1.0))
    s = np.sin(theta)
    return (np.sin((1.0 - u) * theta) * q0 + np.sin(u * theta) * q1) / s


class PoseBuffer:
    """The last `capacity` samples, strictly increasing in time; thread-safe (one writer, many readers)."""

    def __init__(self, capacity: int = 1200, max_gap_s: float = 0.25):
        if capacity < 2 or not (max_gap_s > 0):
            raise ValueError("pose buffer needs capacity >= 2 and max_gap_s > 0")
        self.capacity = capacity
        self.max_gap_s = max_gap_s
        self._times: deque[float] = deque(maxlen=capacity)
        self._samples: deque[PoseSample] = deque(maxlen=capacity)
        self._lock = threading.Lock()

    def __len__(self) -> int:
        return len(self._times)

    def append(self, sample: PoseSample) -> bool:
        """Add a sample newer than every held one; returns False (not added) if it is not newer."""
        with self._lock:
            if self._times and sample.t_fc <= self._times[-1]:
                return False
            self._times.append(sample.t_fc)
            self._samples.append(sample)
            return True

    def clear(self) -> None:
        """Forget every sample (the FC rebooted: its time base restarted)."""
        with self._lock:
            self._times.clear()
            self._samples.clear()

    def span(self) -> tuple[float, float] | None:
        """(oldest, newest) sample times, or None when empty."""
        with self._lock:
            return (self._times[0], self._times[-1]) if self._times else None

    def samples(self) -> list[PoseSample]:
        """A copy of every held sample, oldest first."""
        with self._lock:
            return list(self._samples)

    def latest(self) -> PoseSample | None:
        """The newest sample."""
        with self._lock:
            return self._samples[-1] if self._samples else None

    def at(self, t_fc: float) -> PoseSample:
        """Pose at t_fc: linear in position, slerp in attitude; raises PoseLookupError outside."""
        with self._lock:
            if not self._times:
                raise PoseLookupError("no_pose", "pose buffer is empty")
            first, last = self._times[0], self._times[-1]
            if t_fc < first:
                raise PoseLookupError("before_buffer", f"t={t_fc:.3f} s older than oldest pose {first:.3f} s")
            if t_fc > last:
                raise PoseLookupError("after_buffer", f"t={t_fc:.3f} s newer than newest pose {last:.3f} s")
            i = bisect.bisect_left(self._times, t_fc)  # deque indexing: O(log n) probes, each cheap
            b = self._samples[i]
            if b.t_fc == t_fc:
                return b
            a = self._samples[i - 1]
        gap = b.t_fc - a.t_fc
        if gap > self.max_gap_s:
            raise PoseLookupError("pose_gap", f"poses around t={t_fc:.3f} s are {gap:.3f} s apart")
        u = (t_fc - a.t_fc) / gap
        return PoseSample(
            t_fc, a.position + u * (b.position - a.position), slerp(a.quaternion, b.quaternion, u)
        )

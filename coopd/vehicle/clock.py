"""Flight-controller clock vs our monotonic clock: TIMESYNC round trips, SYSTEM_TIME as fallback."""

from __future__ import annotations

import logging
import math
import threading
from collections import deque
from dataclasses import dataclass

import numpy as np

log = logging.getLogger("coopd.vehicle")

MAX_PENDING = 16
WINDOW = 24
MIN_SKEW_SPAN_S = 1.0
SKEW_LIMITS = (0.5, 1000.0)  # FC seconds per local second; wide because the emulator runs at speed K
TIMESYNC_PREFERRED_FOR_S = 5.0
STEP_MIN_S = 0.005
STEP_STREAK = 3


@dataclass(frozen=True)
class ClockEstimate:
    """fc_time = offset_s + rate * local_time (seconds); uncertainty_s is one sigma in FC seconds."""

    offset_s: float
    rate: float
    uncertainty_s: float
    samples: int
    source: str

    def fc_time(self, local_s: float) -> float:
        return self.offset_s + self.rate * local_s

    def local_time(self, fc_s: float) -> float:
        return (fc_s - self.offset_s) / self.rate


class ClockSync:
    """Keeps recent (local, fc, half-RTT) samples and fits fc = a + b * local over them."""

    def __init__(self, max_rtt_s: float = 0.5, system_time_uncertainty_s: float = 0.02):
        self.max_rtt_s = max_rtt_s
        self.system_time_uncertainty_s = system_time_uncertainty_s
        self._pending: deque[int] = deque(maxlen=MAX_PENDING)
        self._samples: deque[tuple[float, float, float]] = deque(maxlen=WINDOW)
        self._source = "none"
        self._last_timesync_local = -math.inf
        self._estimate: ClockEstimate | None = None
        self._off_streak = 0
        self._lock = threading.Lock()
        self.counters = {
            "timesync_replies": 0,
            "timesync_unmatched": 0,
            "timesync_rtt_rejected": 0,
            "system_time_samples": 0,
            "fc_clock_steps": 0,
            "fc_clock_resets": 0,
        }

    # -- requests and replies -------------------------------------------------------------------

    def new_request(self, local_ns: int) -> int:
        """The ts1 (our time, ns) to send in a TIMESYNC request; remembered to match the reply."""
        with self._lock:
            self._pending.append(int(local_ns))
        return int(local_ns)

    def on_timesync_reply(self, tc1_ns: int, ts1_ns: int, now_local_ns: int) -> bool:
        """Use a TIMESYNC reply (tc1 = FC time, ts1 = our echoed request time); False if refused."""
        with self._lock:
            if ts1_ns not in self._pending:
                self.counters["timesync_unmatched"] += 1
                return False
            self._pending.remove(ts1_ns)
            rtt = (now_local_ns - ts1_ns) * 1e-9
            if not (0.0 <= rtt <= self.max_rtt_s) or tc1_ns <= 0:
                self.counters["timesync_rtt_rejected"] += 1
                return False
            self.counters["timesync_replies"] += 1
            local_mid = (ts1_ns + now_local_ns) * 0.5e-9
            if self._source != "timesync":
                self._samples.clear()  # one-way SYSTEM_TIME samples carry an unknown latency bias
                self._source = "timesync"
            self._last_timesync_local = now_local_ns * 1e-9
            self._add(local_mid, tc1_ns * 1e-9, rtt / 2.0)
            return True

    def on_system_time(self, time_boot_ms: int, now_local_s: float) -> bool:
        """Fallback: SYSTEM_TIME's time_boot_ms, received now; used while TIMESYNC is silent."""
        with self._lock:
            if now_local_s - self._last_timesync_local < TIMESYNC_PREFERRED_FOR_S:
                return False
            if time_boot_ms <= 0:
                return False
            if self._source != "system_time":
                self._samples.clear()
                self._source = "system_time"
            self.counters["system_time_samples"] += 1
            self._add(now_local_s, time_boot_ms * 1e-3, self.system_time_uncertainty_s)
            return True

    def reset(self) -> None:
        """Forget the estimate (FC rebooted)."""
        with self._lock:
            self._samples.clear()
            self._pending.clear()
            self._estimate = None
            self._source = "none"

    # -- estimate -------------------------------------------------------------------------------

    def estimate(self) -> ClockEstimate | None:
        """The current fit, or None before the first sample."""
        with self._lock:
            return self._estimate

    def _add(self, local_s: float, fc_s: float, half_rtt: float) -> None:
        """Add a sample and refit. An FC time far off the prediction means the FC clock restarted;
        STEP_STREAK samples in a row off by more than the fit allows mean it stepped: refit on them."""
        est = self._estimate
        if est is not None and len(self._samples) >= 3:
            err = fc_s - est.fc_time(local_s)
            if abs(err) > max(1.0, 20 * est.uncertainty_s):
                self.counters["fc_clock_resets"] += 1
                log.warning("FC clock jumped by %.3f s against the fit: clock estimate restarted", err)
                self._samples.clear()
                self._off_streak = 0
            elif self._span() >= MIN_SKEW_SPAN_S and abs(err) > max(STEP_MIN_S, 5 * est.uncertainty_s):
                self._off_streak += 1
                if self._off_streak >= STEP_STREAK:
                    self.counters["fc_clock_steps"] += 1
                    log.warning(
                        "FC clock stepped by %.1f ms against the fit: refitting on the newest samples",
                        err * 1e3,
                    )
                    recent = list(self._samples)[-(STEP_STREAK - 1) :]
                    self._samples.clear()
                    self._samples.extend(recent)
                    self._off_streak = 0
            else:
                self._off_streak = 0
        self._samples.append((local_s, fc_s, half_rtt))
        self._estimate = self._fit()

    def _span(self) -> float:
        """Local time covered by the window (the rate is fitted once this reaches MIN_SKEW_SPAN_S)."""
        return self._samples[-1][0] - self._samples[0][0] if self._samples else 0.0

    def _fit(self) -> ClockEstimate:
        """Least-squares line through the best (lowest-RTT) half of the window; rate 1 until it spans 2 s."""
        s = np.array(self._samples)
        if len(s) >= 4:
            keep = s[:, 2] <= np.median(s[:, 2])
            s = s[keep] if keep.sum() >= 2 else s
        local, fc, half = s[:, 0], s[:, 1], s[:, 2]
        rate = 1.0
        if len(s) >= 3 and local.max() - local.min() >= MIN_SKEW_SPAN_S:
            slope = float(np.polyfit(local - local.mean(), fc, 1)[0])
            if SKEW_LIMITS[0] <= slope <= SKEW_LIMITS[1]:
                rate = slope
        offset = float(np.mean(fc - rate * local))
        resid = fc - (offset + rate * local)
        spread = float(np.sqrt(np.mean(resid**2))) if len(s) > 1 else 0.0
        return ClockEstimate(
            offset, rate, spread + rate * float(half.min()), len(self._samples), self._source
        )

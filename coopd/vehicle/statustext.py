"""STATUSTEXT to the FC (which forwards it to the GCS): coopd's events, rate-limited so that a
flapping fault cannot flood a telemetry radio or the operator's screen."""

from __future__ import annotations

import threading
from collections import deque

from pymavlink.dialects.v20 import common as mav

MAX_TEXT = 50
"""Bytes of one STATUSTEXT (a longer text is cut: GCSs show one line per message)."""
SEVERITIES = {
    "emergency": mav.MAV_SEVERITY_EMERGENCY,
    "alert": mav.MAV_SEVERITY_ALERT,
    "critical": mav.MAV_SEVERITY_CRITICAL,
    "error": mav.MAV_SEVERITY_ERROR,
    "warning": mav.MAV_SEVERITY_WARNING,
    "notice": mav.MAV_SEVERITY_NOTICE,
    "info": mav.MAV_SEVERITY_INFO,
    "debug": mav.MAV_SEVERITY_DEBUG,
}


class StatusTextLimiter:
    """Admits at most `burst` texts at once and `per_s` a second on average (a token bucket), and
    the same text at most once per `repeat_s`; what waits to be sent is bounded by `queue`. Every
    refusal is counted. Thread-safe: any stage pushes, the link thread takes."""

    def __init__(self, burst: int = 4, per_s: float = 0.5, repeat_s: float = 10.0, queue: int = 8):
        if burst < 1 or per_s <= 0 or repeat_s < 0 or queue < 1:
            raise ValueError("need burst >= 1, per_s > 0, repeat_s >= 0, queue >= 1")
        self.burst, self.per_s, self.repeat_s = burst, per_s, repeat_s
        self._tokens = float(burst)
        self._refilled: float | None = None
        self._last_sent: dict[bytes, float] = {}
        self._queue: deque[tuple[int, bytes]] = deque()
        self._queue_max = queue
        self._lock = threading.Lock()
        self.counters = {"admitted": 0, "rate_limited": 0, "repeats": 0, "queue_full": 0}

    def push(self, severity: int, text: str, now: float) -> bool:
        """Queue one text (cut to MAX_TEXT bytes of ASCII) unless a limit says no; True if queued."""
        if severity not in SEVERITIES.values():
            raise ValueError(f"{severity} is not a MAV_SEVERITY")
        data = text.encode("ascii", "replace")[:MAX_TEXT]
        with self._lock:
            if self._refilled is not None:
                self._tokens = min(self.burst, self._tokens + (now - self._refilled) * self.per_s)
            self._refilled = now
            last = self._last_sent.get(data)
            if last is not None and now - last < self.repeat_s:
                self.counters["repeats"] += 1
                return False
            if self._tokens < 1.0:
                self.counters["rate_limited"] += 1
                return False
            if len(self._queue) >= self._queue_max:
                self.counters["queue_full"] += 1
                return False
            self._tokens -= 1.0
            self._last_sent[data] = now
            if len(self._last_sent) > 4 * self._queue_max:  # bounded: forget texts outside the window
                self._last_sent = {t: at for t, at in self._last_sent.items() if now - at < self.repeat_s}
            self._queue.append((severity, data))
            self.counters["admitted"] += 1
            return True

    def take(self) -> list[tuple[int, bytes]]:
        """Everything queued, oldest first."""
        with self._lock:
            out = list(self._queue)
            self._queue.clear()
            return out

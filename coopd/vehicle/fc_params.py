"""Whether the flight controller is set up to use obstacle data, read from its parameters.

PX4 uses OBSTACLE_DISTANCE when collision prevention is on (CP_DIST > 0); ArduPilot when a proximity
sensor is of type MAVLink (PRX1_TYPE = 2, PRX_TYPE on releases before 4.3). The link thread asks for
these parameters (PARAM_REQUEST_READ) and feeds every PARAM_VALUE here; any thread may read demand().
"""

from __future__ import annotations

import math
import struct
import threading
from dataclasses import dataclass

from pymavlink.dialects.v20 import common as mav

PX4_PARAMS = ("CP_DIST",)
ARDUPILOT_PARAMS = ("PRX1_TYPE", "PRX_TYPE")
PRX_TYPE_MAVLINK = 2
ASK_PERIOD_S = 2.0
"""Ask again this often while a parameter is unanswered..."""
ASKS_BEFORE_BACKOFF = 5
RECHECK_PERIOD_S = 30.0
"""...and this often once answered or after ASKS_BEFORE_BACKOFF unanswered asks (a changed setting
is also noticed at once from the PARAM_VALUE both stacks send after a PARAM_SET)."""
INT_TYPES = (mav.MAV_PARAM_TYPE_UINT8, mav.MAV_PARAM_TYPE_INT8, mav.MAV_PARAM_TYPE_UINT16,
             mav.MAV_PARAM_TYPE_INT16, mav.MAV_PARAM_TYPE_UINT32, mav.MAV_PARAM_TYPE_INT32)


def watched_params(autopilot: int) -> tuple[str, ...]:
    """The parameters that say whether this autopilot (HEARTBEAT.autopilot) uses obstacle data."""
    if autopilot == mav.MAV_AUTOPILOT_PX4:
        return PX4_PARAMS
    if autopilot == mav.MAV_AUTOPILOT_ARDUPILOTMEGA:
        return ARDUPILOT_PARAMS
    return ()


def param_value(value: float, param_type: int, autopilot: int) -> float | None:
    """A PARAM_VALUE's value as a number: PX4 sends integers bytewise in the float, ArduPilot as a
    float cast; None when it is not a finite number."""
    if autopilot == mav.MAV_AUTOPILOT_PX4 and param_type in INT_TYPES:
        return float(struct.unpack("<i", struct.pack("<f", value))[0])
    return float(value) if math.isfinite(value) else None


def obstacle_demand(autopilot: int, values: dict[str, float]) -> tuple[bool | None, str]:
    """(does the FC use obstacle data, why) from the watched parameters' values; None: not known yet
    (or an autopilot whose setting we do not know)."""
    if autopilot == mav.MAV_AUTOPILOT_PX4:
        if "CP_DIST" not in values:
            return None, "waiting for the FC's CP_DIST"
        cp = values["CP_DIST"]
        return cp > 0, f"CP_DIST = {cp:g} m" + ("" if cp > 0 else " (collision prevention off)")
    if autopilot == mav.MAV_AUTOPILOT_ARDUPILOTMEGA:
        known = {k: v for k, v in values.items() if k in ARDUPILOT_PARAMS}
        if not known:
            return None, "waiting for the FC's PRX1_TYPE"
        asks = any(v == PRX_TYPE_MAVLINK for v in known.values())
        said = ", ".join(f"{k} = {v:g}" for k, v in sorted(known.items()))
        return asks, said + ("" if asks else " (no MAVLink proximity sensor)")
    return None, "an autopilot whose obstacle setting coopd does not know"


@dataclass
class _Ask:
    last_s: float = -math.inf
    count: int = 0
    answered: bool = False


class ObstacleDemandWatch:
    """The FC's obstacle parameters: which to ask for and when (due), what they said (on_value), and
    the resulting demand(). The link thread calls due() and on_value(); demand() is thread-safe."""

    def __init__(self):
        self._lock = threading.Lock()
        self._autopilot = mav.MAV_AUTOPILOT_INVALID
        self._values: dict[str, float] = {}
        self._asks: dict[str, _Ask] = {}
        self.refused = 0
        """PARAM_VALUEs for a watched name whose value was not a finite number."""

    def follow(self, autopilot: int) -> None:
        """The FC we follow is this autopilot (from its HEARTBEAT); a change forgets what was said."""
        with self._lock:
            if autopilot == self._autopilot:
                return
            self._autopilot = autopilot
            self._values.clear()
            self._asks = {name: _Ask() for name in watched_params(autopilot)}

    def due(self, now: float) -> list[str]:
        """The parameters to ask for now (each is marked asked)."""
        out = []
        with self._lock:
            for name, ask in self._asks.items():
                slow = ask.answered or ask.count >= ASKS_BEFORE_BACKOFF
                if now - ask.last_s >= (RECHECK_PERIOD_S if slow else ASK_PERIOD_S):
                    ask.last_s, ask.count = now, ask.count + 1
                    out.append(name)
        return out

    def on_value(self, name: str, value: float, param_type: int) -> bool:
        """One PARAM_VALUE from the FC; True when it was one of the watched parameters."""
        with self._lock:
            if name not in self._asks:
                return False
            number = param_value(value, param_type, self._autopilot)
            if number is None:
                self.refused += 1
                return True
            self._values[name] = number
            self._asks[name].answered = True
            return True

    def demand(self) -> tuple[bool | None, str]:
        with self._lock:
            return obstacle_demand(self._autopilot, dict(self._values))

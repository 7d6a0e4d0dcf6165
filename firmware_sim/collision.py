"""PX4-style collision prevention of the emulated flight controller, and the contacts it is judged by.

OBSTACLE_DISTANCE (MAVLink common) arrives as distances per angular sector; it is kept as 72 body
bins of 5 degrees (0 forward, clockwise, FRD). With CP_DIST > 0 (PX4's parameter; -1 = off, as on
PX4), in position-controlled and offboard flight the horizontal velocity setpoint's component
toward every bin is cut to what lets the vehicle stop CP_DIST short of the obstacle in it:
    room = distance - CP_DIST - (approach speed now) * (age of the data + CP_DELAY)
    allowed = min(sqrt(2 * BRAKE_ACCEL * room), room / CP_DELAY), 0 when room <= 0.
A bin without data (UINT16_MAX, or no message for DATA_TIMEOUT_S) counts as an obstacle at the
vehicle (no motion toward it) unless CP_GO_NO_DATA = 1, as on PX4. A bin reading max_distance + 1
or more is free.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from pymavlink.dialects.v20 import common as mav

BINS = 72
BIN_DEG = 360.0 / BINS
NO_DATA = 65535
DATA_TIMEOUT_S = 0.5
"""PX4 forgets obstacle data older than this."""
BRAKE_ACCEL = 2.0
"""m/s^2 assumed for braking (below the airframe's horizontal acceleration limit, for margin)."""
PROJECTIONS = 16
"""Projections of the setpoint off violated bins per control step (then it is scaled down)."""
BODY_FRAMES = (mav.MAV_FRAME_BODY_FRD,)
NORTH_FRAMES = (mav.MAV_FRAME_GLOBAL, mav.MAV_FRAME_LOCAL_NED)
"""Frames whose angle_offset is measured from north (PX4 accepts these too)."""


@dataclass
class ObstacleBins:
    """One OBSTACLE_DISTANCE as body bins: metres, NaN = no data, inf = free; t: sim time received."""

    distances_m: np.ndarray
    t: float


def bins_from_message(m, yaw_ned: float, t: float) -> ObstacleBins | None:
    """The message's sectors sampled at the 72 body bins' centres; None when it cannot be used (a frame
    other than body FRD / north-aligned, no positive increment, max <= min distance)."""
    if m.frame in BODY_FRAMES:
        turn = 0.0
    elif m.frame in NORTH_FRAMES:
        turn = math.degrees(yaw_ned)  # a north-aligned sector at bearing b is at b - yaw in the body
    else:
        return None
    increment = float(m.increment_f) if m.increment_f > 0 else float(m.increment)
    if not (math.isfinite(increment) and 0 < increment <= 360) or not math.isfinite(m.angle_offset):
        return None
    if m.max_distance <= m.min_distance:
        return None
    values = np.asarray(m.distances, dtype=np.float64)
    count = min(len(values), math.ceil(360.0 / increment - 1e-9))
    out = np.full(BINS, np.nan)
    for b in range(BINS):
        bearing = (b * BIN_DEG + turn - m.angle_offset) % 360.0  # in the message's own frame
        j = int(math.floor(bearing / increment + 0.5)) % max(1, math.ceil(360.0 / increment - 1e-9))
        if j >= count or values[j] == NO_DATA:
            continue
        cm = values[j]
        out[b] = math.inf if cm > m.max_distance else max(cm, m.min_distance) / 100.0
    return ObstacleBins(out, t)


def constrain_velocity(vel_xy, vel_now_xy, yaw_enu: float, bins: ObstacleBins | None, t: float,
                       cp_dist: float, cp_delay: float, go_no_data: bool) -> tuple[np.ndarray, bool]:
    """The horizontal velocity setpoint (ENU) cut toward near or unknown bins; (velocity, cut?).

    Each bin allows an approach speed toward its direction; the setpoint is projected off the most
    violated bin until none is (it slides along a wall), at most PROJECTIONS times, then scaled down
    so that no bin is exceeded whatever the projections left."""
    v = np.array(vel_xy, dtype=np.float64)
    fresh = bins is not None and 0.0 <= t - bins.t <= DATA_TIMEOUT_S
    distances = bins.distances_m if fresh else np.full(BINS, np.nan)
    age = t - bins.t if fresh else 0.0
    theta = yaw_enu - np.radians(np.arange(BINS) * BIN_DEG)  # clockwise body bearing -> ENU angle
    u = np.stack([np.cos(theta), np.sin(theta)], axis=1)
    approach = np.maximum(u @ np.asarray(vel_now_xy, dtype=np.float64), 0.0)
    with np.errstate(invalid="ignore"):
        room = distances - cp_dist - approach * (age + cp_delay)
        allowed = np.minimum(np.sqrt(2.0 * BRAKE_ACCEL * np.maximum(room, 0.0)),
                             np.maximum(room, 0.0) / max(cp_delay, 0.05))
    allowed[np.isnan(distances)] = np.inf if go_no_data else 0.0
    allowed[np.isinf(distances)] = np.inf
    cut = False
    for _ in range(PROJECTIONS):
        excess = u @ v - allowed
        k = int(np.argmax(excess))
        if excess[k] <= 1e-9:
            break
        v -= excess[k] * u[k]
        cut = True
    toward = u @ v
    over = toward > allowed + 1e-9
    if np.any(over):
        v *= float(np.min(np.maximum(allowed[over], 0.0) / toward[over]))
        cut = True
    return v, cut


@dataclass(frozen=True)
class Contact:
    """The vehicle's body began touching something that is not the floor (sim time, geom, where)."""

    t: float
    vehicle: int
    geom: str
    position: tuple[float, float, float]
    speed_m_s: float

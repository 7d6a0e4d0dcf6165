"""The obstacles thread: the map around the vehicle -> MAVLink OBSTACLE_DISTANCE to the FC.

At [obstacles].rate_hz it reads a window around the vehicle's newest pose (the horizontal box within
max range, the band's layers) from the global map (walls peers mapped included) and from the live
local map under the mapping lock, overlays them (the local map is fresher: where it knows a cell it
wins), and hands the 72 sector distances of coopd.grid.sectors to the MAVLink thread, which sends
them. Only the window is copied (at most WINDOW_MAX_CELLS, checked at start), never a whole map.
Without a fresh pose (odometry stale, link down) every sector is sent as "no data", never "free".
It sends always ([obstacles] enabled) or while the FC says it uses obstacle data (when_fc_asks: its
CP_DIST or PRX1_TYPE, coopd.vehicle.fc_params), and computes nothing while it does not send.
"""

import logging
import math
import threading
import time
from collections import deque
from collections.abc import Callable

import numpy as np

from coopd.daemon.config import ObstaclesConfig
from coopd.daemon.threads import run_at_rate
from coopd.grid import OCCUPIED_THRESHOLD
from coopd.grid.sectors import (
    NO_DATA,
    SECTORS,
    band_keys,
    overlay,
    read_window,
    sector_distances_of,
    window_cells,
    window_keys,
)

log = logging.getLogger("coopd.daemon")

WINDOW_MAX_CELLS = 4_000_000
"""Cells one window may hold (two are read per update): a larger range or band at a fine
resolution is refused at start instead of costing the FC link its rate."""
TIMING_WINDOW = 100
"""Updates the status' time per update is the mean and maximum of."""


def yaw_of_quaternion(q) -> float:
    """Heading of body x (FLU) in the ENU map frame, counter-clockwise from east, radians."""
    w, x, y, z = (float(v) for v in q)
    return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def largest_window(config: ObstaclesConfig, resolution: float) -> int:
    """Cells of the biggest window read for this config (the band can straddle one more layer)."""
    z = band_keys(0.0, config.band_below_m, config.band_above_m, resolution)
    lo, hi = window_keys(0.0, 0.0, (z[0], z[1] + 1), config.max_distance_m, resolution)
    return window_cells(lo, hi)


class ObstacleReporter:
    """Owns the obstacle computation and its counters; run() is the coopd-obstacles thread's loop.

    local_map() -> (grid, lock) of the live local map; global_map() -> the merger's (grid, meta) or
    None (installed global maps are never changed, a merge installs a new one); pose() -> the newest
    PoseSample, or None when odometry is stale; send(distances_cm, min_cm, max_cm, t_fc_s);
    fc_demand() -> (does the FC use obstacle data: True, False or None not known, why)."""

    def __init__(self, config: ObstaclesConfig, resolution: float, local_map: Callable, global_map: Callable,
                 pose: Callable, send: Callable, fc_demand: Callable = lambda: (None, "not asked"),
                 threshold: int = OCCUPIED_THRESHOLD):
        cells = largest_window(config, resolution)
        if cells > WINDOW_MAX_CELLS:
            raise ValueError(f"obstacles: max_distance_m {config.max_distance_m} m and the band at "
                             f"{resolution} m cells read {cells} cells per update, more than "
                             f"{WINDOW_MAX_CELLS}; lower max_distance_m or the band")
        self.config = config
        self.resolution = resolution
        self.threshold = threshold
        self.local_map, self.global_map, self.pose, self.send = local_map, global_map, pose, send
        self.fc_demand = fc_demand
        self.sending: bool | None = None
        """Whether the last update sent (None before the first); changes are logged."""
        self.fc_says = "not asked"
        self.min_cm = int(round(config.min_distance_m * 100))
        self.max_cm = int(math.floor(config.max_distance_m * 100 + 1e-6))
        self.counters = {"sent": 0, "no_pose": 0, "with_global": 0, "errors": 0}
        self.last: np.ndarray | None = None
        self._times_s: deque[float] = deque(maxlen=TIMING_WINDOW)
        self.max_s = 0.0
        self._stop = threading.Event()

    def compute(self) -> tuple[np.ndarray, float | None]:
        """(72 distances in cm, FC time of the pose) for the newest pose; all NO_DATA without one."""
        sample = self.pose()
        if sample is None:
            self.counters["no_pose"] += 1
            return np.full(SECTORS, NO_DATA, dtype=np.uint16), None
        c, res = self.config, self.resolution
        x, y, z = (float(v) for v in sample.position)
        zk = band_keys(z, c.band_below_m, c.band_above_m, res)
        lo, hi = window_keys(x, y, zk, c.max_distance_m, res)
        grid, lock = self.local_map()
        with lock:
            window = read_window(grid, lo, hi)
        merged = self.global_map()
        if merged is not None:
            overlay(window, read_window(merged[0], lo, hi))
            self.counters["with_global"] += 1
        distances = sector_distances_of(window, lo, res, (x, y), yaw_of_quaternion(sample.quaternion),
                                        c.min_distance_m, c.max_distance_m, self.threshold)
        return distances, sample.t_fc

    def should_send(self) -> bool:
        """Always with enabled; with when_fc_asks while the FC says it uses obstacle data. A change
        is one log line (waiting for the FC's answer is not one)."""
        asks, self.fc_says = self.fc_demand()
        sending = self.config.enabled or (self.config.when_fc_asks and asks is True)
        if sending == self.sending or (not sending and self.sending is None and asks is None):
            return sending
        self.sending = sending
        c = self.config
        if sending:
            why = "[obstacles] enabled" if c.enabled else f"the FC uses them: {self.fc_says}"
            log.info("obstacles: sending OBSTACLE_DISTANCE at %.1f Hz, %.2f..%.2f m, band %.2f m below to "
                     "%.2f m above (%s)", c.rate_hz, c.min_distance_m, c.max_distance_m, c.band_below_m,
                     c.band_above_m, why)
        else:
            log.info("obstacles: not sending OBSTACLE_DISTANCE: %s", self.fc_says)
        return sending

    def step(self) -> None:
        """One tick of the thread: an update when sending, else nothing."""
        if self.should_send():
            self.update()

    def update(self) -> None:
        """Compute once and hand the message to the MAVLink thread."""
        t0 = time.perf_counter()
        distances, t_fc = self.compute()
        self.send(distances, self.min_cm, self.max_cm, t_fc)
        self.last = distances
        self.counters["sent"] += 1
        spent = time.perf_counter() - t0
        self.max_s = max(self.max_s, spent)
        self._times_s.append(spent)

    def run(self, beat=lambda: None) -> None:
        """Step every 1/rate_hz s until stop(); an error on one update is logged (first three) and
        counted, and the next update comes as usual. beat() each time round (the watchdog's progress)."""
        run_at_rate(self.step, self.config.rate_hz, self._stop, self.counters, "obstacles", beat)

    def stop(self) -> None:
        self._stop.set()

    def status(self) -> dict:
        last = self.last
        times = list(self._times_s)
        return {
            "enabled": self.config.enabled,
            "when_fc_asks": self.config.when_fc_asks,
            "sending": bool(self.sending),
            "fc": self.fc_says,
            "rate_hz": self.config.rate_hz,
            **self.counters,
            "update_ms": None if not times else {"mean": round(1e3 * sum(times) / len(times), 3),
                                                   "max": round(1e3 * self.max_s, 3)},
            "sectors_no_data": None if last is None else int(np.sum(last == NO_DATA)),
            "sectors_free": None if last is None else int(np.sum(last == self.max_cm + 1)),
            "nearest_m": None if last is None or not np.any(last <= self.max_cm)
            else round(float(last[last <= self.max_cm].min()) / 100, 2),
        }

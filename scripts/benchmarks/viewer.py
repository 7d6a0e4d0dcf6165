"""Viewer bandwidth benchmark: what the live view costs on the wire while a map is explored.

A building-like map (--size cells at 0.1 m) is revealed the way a vehicle exploring it at --speed m/s
reveals it (cells within --range m of its path so far, lanes 4 m apart); every second the viewer
ticks once (its 1 Hz rate) and a real Foxglove WebSocket client on loopback, subscribed to /map, /tf
and /track, counts the bytes it receives. Run twice: incremental (only changed bricks, as coopd does)
and full (every brick every tick). /status is left out (its size depends on the daemon, not the map).
Prints JSON and writes out/bench/viewer.json.
Usage: scripts/bench viewer [--size 1M] [--ticks 60] [--speed 1.0] [--range 3.0] [--out PATH]
"""

import argparse
import json
import os
import platform
import sys
import threading
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from coopd.daemon.config import ViewerConfig  # noqa: E402
from coopd.daemon.viewer import BRICK_EDGE, MapViewer  # noqa: E402
from coopd.grid import OCCUPIED_THRESHOLD, OccupancyGrid  # noqa: E402
from coopd.vehicle.pose_buffer import PoseSample  # noqa: E402
from tests.daemon.foxglove_client import FoxgloveClient  # noqa: E402
from tests.sharing.realistic_maps import building_map  # noqa: E402

RESOLUTION = 0.1
GOAL_MBIT_S = 1.0
LANE_M = 4.0
SIZES = {"250k": (100, 100, 25), "1M": (200, 200, 25), "4M": (400, 400, 25)}


def lawnmower(extent_m: tuple[float, float], speed: float, ticks: int, lane_m: float = LANE_M) -> np.ndarray:
    """(ticks, 2) positions one second apart on lanes along x, lane_m apart, from the map's corner."""
    span = extent_m[0] - 2 * lane_m / 2
    out, s = [], 0.0
    for _ in range(ticks):
        lane, along = divmod(s, span + lane_m)
        x = lane_m / 2 + min(along, span) if lane % 2 == 0 else lane_m / 2 + span - min(along, span)
        y = lane_m / 2 + lane * lane_m + max(0.0, along - span)
        out.append((x, min(y, extent_m[1] - lane_m / 2)))
        s += speed
    return np.array(out)


class Exploration:
    """The map as the vehicle has seen it: cells within range of its path, the rest unknown."""

    def __init__(self, truth: np.ndarray, range_m: float):
        self.truth = truth
        self.seen = np.zeros(truth.shape[:2], dtype=bool)
        self.range_cells = range_m / RESOLUTION
        ix, iy = np.meshgrid(np.arange(truth.shape[0]), np.arange(truth.shape[1]), indexing="ij")
        self.ix, self.iy = ix, iy

    def visit(self, xy_m) -> OccupancyGrid:
        cx, cy = (v / RESOLUTION for v in xy_m)
        self.seen |= (self.ix - cx) ** 2 + (self.iy - cy) ** 2 <= self.range_cells ** 2
        cells = np.where(self.seen[:, :, None], self.truth, np.int8(-1))
        return OccupancyGrid(cells, RESOLUTION)


def run(truth: np.ndarray, path: np.ndarray, range_m: float, full: bool) -> dict:
    """Bytes the client received per tick over the path, incremental or full."""
    state = {"merged": None, "sample": None}
    lock = threading.Lock()
    viewer = MapViewer(ViewerConfig(enabled=True, port=0), local_map=lambda: (state["merged"][0], lock),
                       global_map=lambda: state["merged"], pose=lambda: state["sample"],
                       peers=lambda: {}, status=lambda: {})
    viewer.start()
    explore = Exploration(truth, range_m)
    per_tick, changed, tick_ms = [], [], []
    try:
        client = FoxgloveClient(f"ws://127.0.0.1:{viewer.port}", timeout_s=30.0)
        try:
            topics = ["/map", "/tf", "/track"]
            client.subscribe(topics)
            if not viewer.subscribed(topics, 10.0):
                raise RuntimeError(f"the server never saw the subscriptions to {topics}")
            for t, (x, y) in enumerate(path):
                state["merged"] = (explore.visit((x, y)), None)
                state["sample"] = PoseSample(float(t), np.array([x, y, 1.5]), np.array([1.0, 0.0, 0.0, 0.0]))
                if full:
                    viewer.resend_all()
                before_bytes, before_bricks = client.bytes_received, viewer.counters["bricks_sent"]
                t0 = time.perf_counter()
                viewer.tick()
                tick_ms.append(1e3 * (time.perf_counter() - t0))
                while client.next_message()[0] != "/track":  # the tick's last subscribed message
                    pass
                per_tick.append(client.bytes_received - before_bytes)
                changed.append(viewer.counters["bricks_sent"] - before_bricks)
        finally:
            client.close()
    finally:
        viewer.close()
    rates = np.array(per_tick[1:], dtype=np.float64) * 8 / 1e6  # the first tick sends the start map
    return {
        "mbit_s": {"mean": round(float(rates.mean()), 3), "max": round(float(rates.max()), 3)},
        "bytes_first_tick": per_tick[0],
        "bytes_total": int(sum(per_tick)),
        "bricks_sent_per_tick": {"mean": round(float(np.mean(changed[1:])), 1), "max": int(max(changed[1:]))},
        "bricks_non_empty_at_end": len(viewer.tracker.digests),
        "tick_ms": {"median": round(float(np.median(tick_ms)), 1), "max": round(float(max(tick_ms)), 1)},
    }


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", choices=sorted(SIZES), default="1M")
    parser.add_argument("--ticks", type=int, default=60)
    parser.add_argument("--speed", type=float, default=1.0, help="vehicle speed, m/s")
    parser.add_argument("--range", type=float, default=3.0, help="sensor range, m")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--out", default=str(ROOT / "out" / "bench" / "viewer.json"))
    args = parser.parse_args(argv)
    shape = SIZES[args.size]
    truth = building_map(shape, explored=1.0, seed=args.seed)
    extent = (shape[0] * RESOLUTION, shape[1] * RESOLUTION)
    path = lawnmower(extent, args.speed, args.ticks)
    incremental = run(truth, path, args.range, full=False)
    full = run(truth, path, args.range, full=True)
    bricks_total = int(np.prod([-(-s // BRICK_EDGE) for s in shape]))
    result = {
        "benchmark": "viewer",
        "machine": {"python": platform.python_version(), "cpu_count": os.cpu_count(),
                    "processor": platform.processor() or platform.machine(), "load_1min": os.getloadavg()[0]},
        "note": "bytes a real Foxglove WebSocket client on loopback receives on /map, /tf and /track, one "
                "viewer tick per second of exploration; rates leave out the first tick (the start map)",
        "map": {"size": args.size, "shape": list(shape), "cells": int(np.prod(shape)),
                "resolution_m": RESOLUTION, "brick_edge": BRICK_EDGE,
                "occupied_cells": int(np.count_nonzero(truth >= OCCUPIED_THRESHOLD)),
                "bricks": bricks_total},
        "exploration": {"ticks": args.ticks, "rate_hz": 1.0, "speed_m_s": args.speed, "range_m": args.range},
        "incremental": incremental,
        "full": full,
        "full_over_incremental": round(full["mbit_s"]["mean"] / max(incremental["mbit_s"]["mean"], 1e-9), 1),
        "goal_mbit_s": GOAL_MBIT_S,
        "within_goal": incremental["mbit_s"]["mean"] <= GOAL_MBIT_S,
    }
    text = json.dumps(result, indent=2)
    print(text)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(text + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())

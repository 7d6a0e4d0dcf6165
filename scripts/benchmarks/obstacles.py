"""Obstacle distances benchmark: one OBSTACLE_DISTANCE update as the daemon computes it (a window of
the local and of the global map around the vehicle, overlaid, then the numba sector kernel) against
the brute-force numpy reference over the whole map's band, on a large building-like map.

Every update is checked against the reference (identical 72 distances). Times are per update on one
core, the best of --repeat runs per position. Prints JSON and writes out/bench/obstacles.json.
Usage: scripts/bench obstacles [--size 25M] [--positions 20] [--repeat 5] [--seed 1] [--out PATH]
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

from coopd.daemon.config import ObstaclesConfig  # noqa: E402
from coopd.daemon.obstacles import ObstacleReporter, yaw_of_quaternion  # noqa: E402
from coopd.grid import OCCUPIED_THRESHOLD, OccupancyGrid  # noqa: E402
from coopd.grid.sectors import NO_DATA, band_keys  # noqa: E402
from coopd.vehicle.pose_buffer import PoseSample  # noqa: E402
from tests.grid.sector_reference import reference_sectors  # noqa: E402
from tests.sharing.realistic_maps import THESIS_SIZES, building_map  # noqa: E402

RESOLUTION = 0.1
BUDGET_MS = 5.0


def best_of(fn, repeat: int):
    """(result, best seconds) of `repeat` calls."""
    best, out = float("inf"), None
    for _ in range(repeat):
        t = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t)
    return out, best


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--size", default="25M", choices=sorted(THESIS_SIZES))
    p.add_argument("--positions", type=int, default=20)
    p.add_argument("--repeat", type=int, default=5)
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--max-distance", type=float, default=5.0)
    p.add_argument("--out", default=str(ROOT / "out" / "bench" / "obstacles.json"))
    args = p.parse_args(argv)
    shape = THESIS_SIZES[args.size]
    cells = building_map(shape, 0.3, args.seed)
    grid = OccupancyGrid(cells, RESOLUTION, [-(s // 2) for s in shape])
    config = ObstaclesConfig(enabled=True, max_distance_m=args.max_distance)
    lock = threading.Lock()
    rng = np.random.default_rng(args.seed)
    sample = [None]
    reporter = ObstacleReporter(config, RESOLUTION, lambda: (grid, lock), lambda: (grid, None),
                                lambda: sample[0], lambda *m: None)
    lo, hi = grid.bounds_m()
    sample[0] = PoseSample(0.0, np.zeros(3), np.array([1.0, 0, 0, 0]))
    reporter.compute()  # compile (or load) the kernel
    rows, agree = [], 0
    for k in range(args.positions):
        pos = np.array([rng.uniform(lo[0] + 2, hi[0] - 2), rng.uniform(lo[1] + 2, hi[1] - 2),
                        rng.uniform(lo[2] + 1, hi[2] - 1)])
        yaw = rng.uniform(-np.pi, np.pi)
        q = np.array([np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2)])
        sample[0] = PoseSample(float(k), pos, q)
        (got, _), kernel_s = best_of(reporter.compute, args.repeat)
        zk = band_keys(pos[2], config.band_below_m, config.band_above_m, RESOLUTION)
        want, reference_s = best_of(lambda: reference_sectors(  # noqa: B023
            grid, zk, pos, yaw_of_quaternion(q), config.min_distance_m, config.max_distance_m,  # noqa: B023
            OCCUPIED_THRESHOLD), max(1, args.repeat // 2))
        same = bool(np.array_equal(got, want))
        agree += same
        rows.append({"position_m": [round(float(v), 2) for v in pos],
                     "yaw_deg": round(float(np.degrees(yaw)), 1),
                     "update_ms": round(kernel_s * 1e3, 3), "reference_ms": round(reference_s * 1e3, 2),
                     "agree": same, "no_data_sectors": int(np.sum(got == NO_DATA)),
                     "obstacle_sectors": int(np.sum(got <= reporter.max_cm))})
        print(f"  {k:3d} update {kernel_s * 1e3:7.3f} ms  reference {reference_s * 1e3:8.2f} ms  "
              f"{'agree' if same else 'DIFFER'}", file=sys.stderr, flush=True)
    update = np.array([r["update_ms"] for r in rows])
    reference = np.array([r["reference_ms"] for r in rows])
    result = {
        "benchmark": "obstacles",
        "machine": {"python": platform.python_version(), "cpu_count": os.cpu_count(),
                    "processor": platform.processor() or platform.machine(), "load_1min": os.getloadavg()[0]},
        "note": "one update as the daemon computes it (local + global window, overlay, numba kernel) vs the "
                "numpy reference over the whole map's band; best of --repeat per position, one core",
        "map": {"size": args.size, "shape": list(shape), "cells": int(grid.size), "resolution_m": RESOLUTION},
        "config": {"max_distance_m": config.max_distance_m, "min_distance_m": config.min_distance_m,
                   "band_below_m": config.band_below_m, "band_above_m": config.band_above_m},
        "positions": args.positions,
        "update_ms": {"median": round(float(np.median(update)), 3), "max": round(float(update.max()), 3)},
        "reference_ms": {"median": round(float(np.median(reference)), 2)},
        "speedup_median": round(float(np.median(reference / update)), 1),
        "agree": agree,
        "within_budget": bool(update.max() <= BUDGET_MS),
        "budget_ms": BUDGET_MS,
        "rows": rows,
    }
    text = json.dumps(result, indent=2)
    print(text)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(text + "\n")
    return 0 if agree == args.positions else 1


if __name__ == "__main__":
    sys.exit(main())

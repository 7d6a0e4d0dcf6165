"""Full searches run ahead on worker threads ([merging] search_threads) against one at a time.

The case they serve: a drone merging maps it never fitted before (the swarm's lowest vehicle id
when every map arrives at once). Their fits are held provisional, so the global map does not change
between the searches and two can run at a time with the results of one at a time. Input: the
cached flight of `--drones` drones in `--world` (firmware_sim/simset.py): drone 1's map is the
reference, every other map is searched. Both ways alternate --repeat times in one process (the
machine is shared: the ratio of the medians is the figure); every run's results are checked
identical to the first one-at-a-time run. Wall and CPU (the process's, worker threads included).
Usage: scripts/bench merge_ahead [--world small_house] [--drones 10] [--repeat 5] [--workers 2]
JSON in out/bench/merge_ahead.json.
"""

import argparse
import json
import os
import statistics
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path[:0] = [str(ROOT)]

from coopd.merging.multi import merge_all  # noqa: E402
from coopd.merging.params import coopd_params  # noqa: E402
from firmware_sim import simset  # noqa: E402


def same_results(a, b) -> bool:
    """Whether two merge_all results agree exactly (transforms, decisions, scores, global map)."""
    return all(np.array_equal(x.transform, y.transform) and (x.accepted, x.reason, x.score) ==
               (y.accepted, y.reason, y.score) for x, y in zip(a.results, b.results, strict=True)) \
        and np.array_equal(a.global_map.cells, b.global_map.cells)


def timed(fn):
    t0, c0 = time.perf_counter(), time.process_time()
    out = fn()
    return out, time.perf_counter() - t0, time.process_time() - c0


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--world", default="small_house")
    ap.add_argument("--drones", type=int, default=10)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--out", type=Path, default=ROOT / "out" / "bench" / "merge_ahead.json")
    args = ap.parse_args()
    maps = simset.flight_maps(args.world, args.seed, args.drones, cache_dir=ROOT / simset.CACHE_DIR)
    params = coopd_params()
    reference, others = maps[0].grid, [m.grid for m in maps[1:]]
    merge_all(reference, others[:1], params)  # kernels loaded before anything is timed

    def run(workers):
        return merge_all(reference, others, params, hold=lambda i, r: True, ahead=lambda i: True,
                         workers=workers)

    runs = {1: [], args.workers: []}
    first = None
    identical = True
    for _ in range(args.repeat):
        for workers in runs:
            result, wall, cpu = timed(lambda w=workers: run(w))
            first = first or result
            identical &= same_results(first, result)
            runs[workers].append({"wall_s": round(wall, 3), "cpu_s": round(cpu, 3)})
    summary = {w: {k: round(statistics.median(r[k] for r in rs), 3) for k in ("wall_s", "cpu_s")}
               for w, rs in runs.items()}
    out = {
        "bench": "merge_ahead", "world": args.world, "drones": args.drones, "searches": len(others),
        "cpus": os.cpu_count(), "load_avg_1min": round(os.getloadavg()[0], 2), "identical": identical,
        "one_at_a_time": summary[1], f"{args.workers}_at_a_time": summary[args.workers],
        "wall_ratio": round(summary[args.workers]["wall_s"] / summary[1]["wall_s"], 3),
        "cpu_ratio": round(summary[args.workers]["cpu_s"] / summary[1]["cpu_s"], 3),
        "runs": {str(w): rs for w, rs in runs.items()},
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(out, indent=1))
    print(json.dumps({k: v for k, v in out.items() if k != "runs"}))


if __name__ == "__main__":
    main()

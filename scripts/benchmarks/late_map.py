"""A map that reaches the lowest id after it fused the others: placed, or left out (docs/merging.md).

The lowest vehicle id of a swarm searches every map it holds; the others wait for its result. A map
that reaches it after it fused the others is searched on the global map of all of them, many times
the map's size. For each vehicle X of a simset flight: drone 1's merge with the other maps fused (by
their own accepted transforms, as the daemon's next merge does) and X last. Reported per X: the
search on the global map alone (what merge_all ran before it searched such a refusal again on the
reference alone) and merge_all's result, both judged against the flight's truth
(within --tol-m and --tol-deg, as scripts/bench swarm judges a merge).
Usage: scripts/bench late_map [--world bookstore] [--vehicles 30] [--maps 2,10,30]
"""

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from coopd.merging import Hint, merge_all  # noqa: E402
from coopd.merging.pair import merge_prepared, prepare  # noqa: E402
from coopd.merging.params import coopd_params  # noqa: E402
from firmware_sim import simset  # noqa: E402
from firmware_sim.accuracy import offset_error  # noqa: E402


def judged(r, truth: np.ndarray, tol_m: float, tol_deg: float) -> dict:
    """A result as the table shows it: placed right, placed wrong, or refused (with the reason)."""
    te, re = offset_error(r.transform, truth)
    verdict = "refused" if not r.accepted else "right" if te < tol_m and re < tol_deg else "wrong"
    return {"verdict": verdict, "error_m": round(te, 3), "error_deg": round(re, 2),
            "score": round(r.score, 3), "overlap": round(r.overlap, 3), "reason": r.reason}


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--world", default="bookstore")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--vehicles", type=int, default=30)
    ap.add_argument("--maps", default="",
                    help="vehicle ids to bring last, comma-separated (default: all but 1)")
    ap.add_argument("--tol-m", type=float, default=0.3)
    ap.add_argument("--tol-deg", type=float, default=3.0)
    ap.add_argument("--out", default=str(ROOT / "out" / "bench" / "late_map.json"))
    args = ap.parse_args()
    flight = simset.flight_maps(args.world, args.seed, args.vehicles, cache_dir=ROOT / simset.CACHE_DIR)
    params = coopd_params()
    ref, others = flight[0], flight[1:]
    truths = [simset.truth_b_to_a(ref, m) for m in others]
    # Every fit as drone 1's first merge finds it: each map searched on drone 1's map alone (all held).
    first = merge_all(ref.grid, [m.grid for m in others], params, hold=lambda i, r: True)
    wanted = [int(v) for v in args.maps.split(",") if v] or [m.vehicle for m in others]
    rows = []
    for x in [k for k, m in enumerate(others) if m.vehicle in wanted]:
        rest = [k for k in range(len(others)) if k != x and first.results[k].accepted]
        hints = [[Hint(first.results[k].transform, "own")] for k in rest] + [[]]
        t0 = time.thread_time()
        res = merge_all(ref.grid, [others[k].grid for k in rest] + [others[x].grid], params, hints=hints)
        cpu_s = time.thread_time() - t0
        fused = merge_all(ref.grid, [others[k].grid for k in rest], params, hints=hints[:-1]).global_map
        tm: dict = {}
        alone = merge_prepared(prepare(fused, params, tm), prepare(others[x].grid, params, tm), params, tm)
        row = {"vehicle": others[x].vehicle, "fused_before": len(rest),
               "global_map_only": judged(alone, truths[x], args.tol_m, args.tol_deg),
               "merge_all": judged(res.results[-1], truths[x], args.tol_m, args.tol_deg),
               "full_registrations": res.full_registrations, "merge_cpu_s": round(cpu_s, 2)}
        rows.append(row)
        print(json.dumps(row), file=sys.stderr, flush=True)
    count = {k: {v: sum(r[k]["verdict"] == v for r in rows) for v in ("right", "wrong", "refused")}
             for k in ("global_map_only", "merge_all")}
    conditions = {"world": args.world, "seed": args.seed, "vehicles": args.vehicles,
                  "tol": [args.tol_m, args.tol_deg]}
    result = {"bench": "late_map", "conditions": conditions,
              "first_merge_accepted": sum(r.accepted for r in first.results), "maps": rows, "count": count}
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_suffix(".tmp")
    tmp.write_text(json.dumps(result, indent=1))
    tmp.replace(out)
    print(json.dumps({k: v for k, v in result.items() if k != "maps"}, indent=1))


if __name__ == "__main__":
    main()

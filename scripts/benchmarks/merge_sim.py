"""Merging on real flight maps: firmware_sim drones map with drifting odometry (firmware_sim/simset.py).

For every world and seed, every ordered pair of drones goes through merge_pair (correct: within
--tol-m / --tol-deg of the truth at t = 0). Wrong candidates must be rejected: pairs of maps from
different worlds (full pipeline) and each correct pair's true transform perturbed by 1-3 m and/or
10-90 deg, refined and validated as a search hypothesis would be (pair.judge).
Prints a per-world table and writes out/bench/merge_sim.json.
Usage: scripts/benchmarks/merge_sim.py [--worlds a,b] [--seeds 1,2] [--vehicles 3] [--laps 1] [--ground-s 0]
       [--pose-delay-s 0] [--set name=value,...] [--mapper name=value,...]
--mapper maps the flights with other MapperConfig settings (e.g. graze_deg=0); they are cached apart.
"""

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from _overrides import overrides  # noqa: E402

from coopd.geometry import rigid, rotation_angle_deg, rotation_z  # noqa: E402
from coopd.mapping import MapperConfig  # noqa: E402
from coopd.merging.pair import judge, merge_prepared, prepare  # noqa: E402
from coopd.merging.params import coopd_params  # noqa: E402
from firmware_sim import simset  # noqa: E402

PERTURBATIONS = [(1.0, 0.0), (2.0, 0.0), (3.0, 0.0), (0.0, 10.0), (0.0, 30.0), (0.0, 90.0), (1.5, 20.0),
                 (2.5, 45.0)]
"""(shift m, yaw deg) applied to the true transform of every pair."""


def key(m):
    return m.world, m.seed, m.vehicle


def errors(t, truth):
    """(translation error m, rotation error deg)."""
    return float(np.linalg.norm(t[:3, 3] - truth[:3, 3])), rotation_angle_deg(t[:3, :3].T @ truth[:3, :3])


def perturbed(truth, shift_m, yaw_deg, k):
    """truth moved by shift_m in direction k*137.5 deg and turned by yaw_deg about b's map origin."""
    a = math.radians(137.5 * k)
    return rigid(translation=[shift_m * math.cos(a), shift_m * math.sin(a), 0.0]) @ truth @ \
        rigid(rotation_z(math.radians(yaw_deg)))


def row(r, truth, true_overlap, seconds, tol_m, tol_deg):
    te, re = errors(r.transform, truth)
    return {"accepted": r.accepted, "correct": te <= tol_m and re <= tol_deg, "trans_err_m": round(te, 3),
            "rot_err_deg": round(re, 2), "score": round(r.score, 4), "overlap": round(r.overlap, 3),
            "true_overlap": round(true_overlap, 3), "agree": r.agreement, "conflicts": r.conflicts,
            "runner_up_score": round(r.runner_up_score, 4), "reason": r.reason, "seconds": round(seconds, 2)}


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--worlds", default=",".join(simset.WORLDS))
    ap.add_argument("--seeds", default="1,2")
    ap.add_argument("--vehicles", type=int, default=3)
    ap.add_argument("--laps", type=int, default=1, help="times each drone flies its route (more drift)")
    ap.add_argument("--ground-s", type=float, default=0.0, help="seconds mapped on the ground before takeoff")
    ap.add_argument("--pose-delay-s", type=float, default=0.0, help="pose lag of each frame")
    ap.add_argument("--tol-m", type=float, default=0.3)
    ap.add_argument("--tol-deg", type=float, default=3.0)
    ap.add_argument("--set", default="", help="parameter overrides, e.g. min_score=0.96,min_margin=0.1")
    ap.add_argument("--mapper", default="", help="mapper settings of the flights, e.g. graze_deg=0")
    ap.add_argument("--out", default="out/bench/merge_sim.json")
    args = ap.parse_args()
    try:
        params = coopd_params().with_(**overrides(args.set, coopd_params()))
        mapper = MapperConfig(**overrides(args.mapper, MapperConfig()))
    except (ValueError, TypeError) as e:
        ap.error(str(e))
    flights = [simset.flight_maps(w, int(s), args.vehicles, args.laps, args.ground_s,
                                  args.pose_delay_s, mapper=mapper) for w in args.worlds.split(",")
               for s in args.seeds.split(",")]
    report = {"params": {k: getattr(params, k) for k in ("min_score", "min_agreement", "min_overlap",
                                                         "min_margin", "refine_iterations")},
              "pairs": [], "cross_world": [], "perturbed": []}
    prepared = {}
    for maps in flights:
        for m in maps:
            prepared[key(m)] = prepare(m.grid, params)
    for maps in flights:
        for a in maps:
            for b in maps:
                if a.vehicle == b.vehicle:
                    continue
                truth = simset.truth_b_to_a(a, b)
                t0 = time.perf_counter()
                r = merge_prepared(prepared[key(a)], prepared[key(b)], params)
                rr = row(r, truth, simset.known_overlap(a.grid, b.grid, truth), time.perf_counter() - t0,
                         args.tol_m, args.tol_deg)
                rr |= {"world": a.world, "seed": a.seed, "a": a.vehicle, "b": b.vehicle}
                report["pairs"].append(rr)
                print(json.dumps(rr), file=sys.stderr)
                if a.vehicle > b.vehicle:
                    continue
                for k, (shift, yaw) in enumerate(PERTURBATIONS):
                    start = perturbed(truth, shift, yaw, k)
                    j = judge(prepared[key(a)], prepared[key(b)], start, params)
                    pr = row(j, truth, 0.0, 0.0, args.tol_m, args.tol_deg)
                    pr |= {"world": a.world, "seed": a.seed, "a": a.vehicle, "b": b.vehicle, "shift_m": shift,
                           "yaw_deg": yaw}
                    report["perturbed"].append(pr)
    for i, maps in enumerate(flights):
        a = maps[0]
        b = flights[(i + 2) % len(flights)][1] if len(flights) > 2 else None
        if b is None or b.world == a.world:
            continue
        t0 = time.perf_counter()
        r = merge_prepared(prepared[key(a)], prepared[key(b)], params)
        rr = {"a": f"{a.world}/{a.seed}/{a.vehicle}", "b": f"{b.world}/{b.seed}/{b.vehicle}",
              "accepted": r.accepted, "score": round(r.score, 4), "overlap": round(r.overlap, 3),
              "agree": r.agreement, "reason": r.reason, "seconds": round(time.perf_counter() - t0, 2)}
        report["cross_world"].append(rr)
        print(json.dumps(rr), file=sys.stderr)
    report["summary"] = summarise(report)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(report, indent=1))
    print(json.dumps(report["summary"], indent=1))


def summarise(report):
    """Per world: pairs, accepted, correct, wrong; overall wrong candidates accepted."""
    out = {}
    for w in sorted({r["world"] for r in report["pairs"]}):
        rows = [r for r in report["pairs"] if r["world"] == w]
        ok = [r for r in rows if r["accepted"] and r["correct"]]
        out[w] = {"pairs": len(rows), "accepted": sum(r["accepted"] for r in rows), "correct": len(ok),
                  "wrong": sum(r["accepted"] and not r["correct"] for r in rows),
                  "true_overlap": [min(r["true_overlap"] for r in rows),
                                   max(r["true_overlap"] for r in rows)],
                  "score": [min(r["score"] for r in rows), max(r["score"] for r in rows)],
                  "worst_accepted_err": [max((r["trans_err_m"] for r in ok), default=None),
                                         max((r["rot_err_deg"] for r in ok), default=None)],
                  "median_seconds": float(np.median([r["seconds"] for r in rows]))}
    pert = report["perturbed"]
    wrong_pert = [r for r in pert if r["accepted"] and not r["correct"]]
    out["perturbed"] = {"candidates": len(pert), "wrong_accepted": len(wrong_pert),
                        "refined_back_to_truth": sum(r["correct"] for r in pert),
                        "max_wrong_score": max((r["score"] for r in pert if not r["correct"]), default=None)}
    cw = report["cross_world"]
    out["cross_world"] = {"pairs": len(cw), "accepted": sum(r["accepted"] for r in cw),
                          "max_score": max((r["score"] for r in cw), default=None)}
    return out


if __name__ == "__main__":
    main()

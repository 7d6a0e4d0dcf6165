"""Distributed merging (docs/merging.md): what hints save, on benchset maps.

1. Pairs: CPU (time.thread_time) of merge_all(a, [b]) by full registration vs with the accepted
   transform as an own hint (the next merge of the same pair), and a wrong hint (true transform
   moved 2 m and 30 deg), which must be refused and fall back to the full search.
2. Swarm: N drones of a chain of maps, each merging all the others' maps once, in turn; with
   distributed, each drone uses the results the earlier ones published (hints_for) and publishes
   its own. Counts full registrations and sums CPU across the swarm, then a second pass (own warm
   start) on each drone.
Usage: scripts/bench merge_hints [--pairs 12] [--drones 4]
"""

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from coopd.geometry import invert, rigid, rotation_angle_deg, rotation_z  # noqa: E402
from coopd.merging import Hint, merge_all  # noqa: E402
from coopd.merging.hints import hints_for  # noqa: E402
from coopd.sharing.wire import MergeEdge, MergeResultMessage  # noqa: E402
from firmware_sim.benchset import benchmark_pairs, make_chain, make_world  # noqa: E402


def _cpu(fn):
    t0 = time.thread_time()
    out = fn()
    return out, time.thread_time() - t0


def _error(t, truth) -> tuple[float, float]:
    return (float(np.linalg.norm(t[:3, 3] - truth[:3, 3])),
            rotation_angle_deg(t[:3, :3].T @ truth[:3, :3]))


def pairs(count: int) -> dict:
    rows = []
    for p in benchmark_pairs(count=count, non_overlapping=0):
        full, cpu_full = _cpu(lambda p=p: merge_all(p.a, [p.b]))
        r = full.results[0]
        row = {"seed": p.seed, "overlap": round(p.overlap, 3), "full_accepted": r.accepted,
               "cpu_full_s": round(cpu_full, 3)}
        if r.accepted:
            hinted, cpu_hint = _cpu(lambda p=p, t=r.transform: merge_all(p.a, [p.b], hints=[[Hint(t)]]))
            wrong = rigid(rotation_z(np.radians(30)), [2.0, 0.0, 0.0]) @ p.a_from_b
            bad, cpu_bad = _cpu(lambda p=p, t=wrong: merge_all(p.a, [p.b], hints=[[Hint(t, "peer")]]))
            h, b = hinted.results[0], bad.results[0]
            row |= {"hint_method": h.method, "cpu_hint_s": round(cpu_hint, 3),
                    "hint_error_m_deg": [round(v, 3) for v in _error(h.transform, p.a_from_b)],
                    "wrong_hint_refused": bad.hints_refused[0] == 1, "wrong_hint_then": b.method,
                    "wrong_then_accepted": b.accepted, "cpu_wrong_s": round(cpu_bad, 3)}
        rows.append(row)
    ok = [r for r in rows if r["full_accepted"] and r.get("hint_method") == "hint:own"]
    ratio = [r["cpu_full_s"] / r["cpu_hint_s"] for r in ok]
    return {"pairs": len(rows), "full_accepted": sum(r["full_accepted"] for r in rows),
            "hint_accepted": len(ok),
            "wrong_hints_refused": sum(r.get("wrong_hint_refused", False) for r in rows),
            "median_cpu_full_s": round(float(np.median([r["cpu_full_s"] for r in ok])), 3) if ok else None,
            "median_cpu_hint_s": round(float(np.median([r["cpu_hint_s"] for r in ok])), 3) if ok else None,
            "median_ratio_full_over_hint": round(float(np.median(ratio)), 2) if ratio else None,
            "rows": rows}


def swarm(drones: int, distributed: bool, maps) -> dict:
    """Each drone in turn merges all others' maps, twice (the second time with its own hints)."""
    published: dict[int, MergeResultMessage] = {}
    own: dict[int, dict[int, np.ndarray]] = {d: {} for d in range(drones)}
    out = {"distributed": distributed, "passes": []}
    for _ in range(2):
        full = hinted_own = hinted_peer = refused = wrong = 0
        cpu = 0.0
        for d in range(drones):
            vids = [v for v in range(drones) if v != d]
            peer = [m for v, m in published.items() if v != d] if distributed else []
            hints = hints_for(d, vids, own[d], peer)
            others = [maps[v].grid for v in vids]
            ref = maps[d].grid
            res, c = _cpu(lambda ref=ref, others=others, hints=hints: merge_all(ref, others, hints=hints))
            cpu += c
            full += res.full_registrations
            refused += sum(res.hints_refused)
            edges = []
            for v, r in zip(vids, res.results, strict=True):
                hinted_own += r.method == "hint:own"
                hinted_peer += r.method == "hint:peer"
                if r.accepted:
                    truth = invert(maps[d].world_from_map) @ maps[v].world_from_map
                    e_m, e_deg = _error(r.transform, truth)
                    wrong += e_m > 0.3 or e_deg > 2.0
                    own[d][v] = r.transform
                    edges.append(MergeEdge(d, v, r.transform, r.score, r.overlap, 1, 1))
            if distributed and edges:
                published[d] = MergeResultMessage(d, len(out["passes"]) + 1, 0.0, tuple(edges))
        out["passes"].append({"full_registrations": full, "hinted_own": hinted_own,
                              "hinted_peer": hinted_peer, "hint_rejected": refused,
                              "wrong_transforms": wrong, "cpu_s": round(cpu, 2)})
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--pairs", type=int, default=12)
    ap.add_argument("--drones", type=int, default=4)
    args = ap.parse_args()
    world = make_world(0)
    centres = [(6.0 + 4.0 * i, 12.5) for i in range(args.drones)]
    maps = make_chain(world, 3, centres)
    report = {"pairs": pairs(args.pairs),
              "swarm": [swarm(args.drones, False, maps), swarm(args.drones, True, maps)]}
    text = json.dumps(report, indent=1)
    print(text)
    out = Path(__file__).resolve().parents[2] / "out" / "bench"
    out.mkdir(parents=True, exist_ok=True)
    (out / "merge_hints.json").write_text(text)


if __name__ == "__main__":
    main()

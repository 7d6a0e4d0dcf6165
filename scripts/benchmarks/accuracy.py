"""Accuracy against ground truth in every world: runs scripts/demo (3 drones, default noise) once per
world, one after another, and gathers each run's demo_report.json into out/bench/accuracy.json and a
markdown table (out/bench/accuracy.md): per drone, occupied-cell precision/recall of its global map
in the region explored, merged pairs, worst offset error of its merged maps, wall time.

Goal (issue #7): precision and recall >= 0.85, offsets within 0.3 m and 3 deg.
Usage: scripts/benchmarks/accuracy.py [--worlds a,b] [--drones 3] [--seed 1] [--speed 2]
                                     [--autopilot px4|ardupilot] [--timeout 270] [--tabulate]
                                     [--network auto|netns|loopback] [--port-base N]
(--tabulate: no runs, the table again from the reports already in out/bench/accuracy/WORLD/)
--autopilot ardupilot flies ArduCopter-personality drones (coopd builds its poses from
LOCAL_POSITION_NED + ATTITUDE_QUATERNION) and writes out/bench/accuracy-ardupilot.{json,md} and
out/bench/accuracy-ardupilot/WORLD/, beside the PX4 run's files.
"""

import argparse
import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from firmware_sim.worlds import GENERATORS  # noqa: E402

GOAL = {"precision": 0.85, "recall": 0.85, "error_m": 0.3, "error_deg": 3.0}


def drone_rows(report: dict) -> list[dict]:
    """One row per drone of a demo_report.json: global-map precision/recall, merges, worst offset."""
    rows = []
    for d in report.get("accuracy", []):
        g, loc = d.get("global") or {}, d.get("local") or {}
        merged = [p for p in d["pairs"] if p["merged"]]
        rows.append({
            "world": report["world"], "drone": d["drone"],
            "precision": g.get("precision"), "recall": g.get("recall"),
            "precision_tol1": g.get("precision_tol1"), "recall_tol1": g.get("recall_tol1"),
            "local_precision": loc.get("precision"), "local_recall": loc.get("recall"),
            "merged": len(merged), "pairs": len(d["pairs"]),
            "max_error_m": max((p["error_m"] for p in merged), default=None),
            "max_error_deg": max((p["error_deg"] for p in merged), default=None),
            "drift_m": loc.get("drift_m"), "drift_deg": loc.get("drift_deg"),
            "wall_s": round(report["elapsed_s"]), "sim_s": round(report.get("sim_s", 0.0)),
        })
    return rows


def meets_goal(r: dict) -> bool:
    """Precision, recall and every merged offset within the goal, and every pair merged."""
    return (r["precision"] is not None and r["precision"] >= GOAL["precision"]
            and r["recall"] >= GOAL["recall"] and r["merged"] == r["pairs"]
            and (r["max_error_m"] or 0.0) <= GOAL["error_m"]
            and (r["max_error_deg"] or 0.0) <= GOAL["error_deg"])


def fmt(v, spec: str) -> str:
    return "-" if v is None else format(v, spec)


def markdown(rows: list[dict]) -> str:
    """The table for docs/accuracy.md."""
    lines = ["| world | drone | precision | recall | P / R within 1 cell | own map P / R | merged pairs "
             "| max offset error m / deg | drift m / deg | wall s | goal |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(
            f"| {r['world']} | {r['drone']} | {fmt(r['precision'], '.3f')} | {fmt(r['recall'], '.3f')} "
            f"| {fmt(r['precision_tol1'], '.3f')} / {fmt(r['recall_tol1'], '.3f')} "
            f"| {fmt(r['local_precision'], '.3f')} / {fmt(r['local_recall'], '.3f')} "
            f"| {r['merged']}/{r['pairs']} "
            f"| {fmt(r['max_error_m'], '.2f')} / {fmt(r['max_error_deg'], '.1f')} "
            f"| {fmt(r['drift_m'], '.2f')} / {fmt(r['drift_deg'], '.2f')} | {r['wall_s']} "
            f"| {'yes' if meets_goal(r) else 'no'} |")
    return "\n".join(lines) + "\n"


def run_world(world: str, a, out: Path) -> list[dict]:
    """One demo run (or, with --tabulate, the report of the last); its rows (none without a report)."""
    run_out = out / run_name(a) / world
    run_out.mkdir(parents=True, exist_ok=True)
    report_path = run_out / "demo_report.json"
    if a.tabulate:
        return drone_rows(json.loads(report_path.read_text())) if report_path.exists() else []
    report_path.unlink(missing_ok=True)
    cmd = [sys.executable, str(ROOT / "scripts" / "demo.py"), "--world", world, "--drones", str(a.drones),
           "--seed", str(a.seed), "--speed", str(a.speed), "--autopilot", a.autopilot, "--out", str(run_out),
           "--timeout", str(a.timeout), "--network", a.network]
    if a.port_base is not None:
        cmd += ["--port-base", str(a.port_base)]
    with open(run_out / "demo.log", "wb") as log:
        rc = subprocess.call(cmd, stdout=log, stderr=subprocess.STDOUT, cwd=ROOT)
    if not report_path.exists():
        print(f"accuracy: {world}: demo exited {rc} without a report; see {run_out / 'demo.log'}")
        return []
    rows = drone_rows(json.loads(report_path.read_text()))
    print(markdown(rows), flush=True)
    return rows


def run_name(a) -> str:
    """Where a run's files go: 'accuracy' for PX4 (as before), 'accuracy-ardupilot' for ArduPilot."""
    return "accuracy" if a.autopilot == "px4" else f"accuracy-{a.autopilot}"


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--worlds", default=",".join(GENERATORS))
    p.add_argument("--drones", type=int, default=3)
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--speed", type=float, default=2.0)
    p.add_argument("--out", type=Path, default=ROOT / "out" / "bench")
    p.add_argument("--autopilot", choices=("px4", "ardupilot"), default="px4")
    p.add_argument("--timeout", type=float, default=270.0,
                   help="each demo's wall-time limit (more on a loaded machine: merging takes CPU)")
    p.add_argument("--network", choices=("auto", "netns", "loopback"), default="auto",
                   help="the demo's network; loopback with its own --port-base runs beside another swarm "
                        "(two netns swarms share the FC cables' root-side addresses)")
    p.add_argument("--port-base", type=int, default=None, help="the demo's --port-base")
    p.add_argument("--tabulate", action="store_true", help="no runs: tabulate the reports already there")
    a = p.parse_args()
    worlds = [w for w in a.worlds.split(",") if w]
    unknown = sorted(set(worlds) - set(GENERATORS))
    if unknown:
        p.error(f"unknown worlds {unknown}; known: {sorted(GENERATORS)}")
    a.out.mkdir(parents=True, exist_ok=True)
    rows = []
    for world in worlds:
        print(f"accuracy: {world} ...", flush=True)
        rows += run_world(world, a, a.out)
        name = run_name(a)
        summary = {"goal": GOAL, "autopilot": a.autopilot, "drones": a.drones, "seed": a.seed,
                   "speed": a.speed, "rows": rows}
        (a.out / f"{name}.json").write_text(json.dumps(summary, indent=1))
        (a.out / f"{name}.md").write_text(markdown(rows))
    print(markdown(rows))
    print(f"wrote {a.out / (run_name(a) + '.json')} and {a.out / (run_name(a) + '.md')}")
    return 0 if rows and all(meets_goal(r) for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())

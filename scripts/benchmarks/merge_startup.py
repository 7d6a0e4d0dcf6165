"""How long a fresh `coopctl map merge` process takes before it does any merging work.

A fresh interpreter (as coopctl is) imports coopctl's merge path, then merges one real pair twice:
the first merge also loads every numba kernel it meets from the on-disk cache (or compiles it), the
second runs warm. Ready = interpreter start + imports + (first merge - second merge). The peer in
the same run is a bare interpreter that imports numpy (what any numerical Python tool pays).
Wall and CPU (the child's process time) per phase, median of --repeat fresh processes.

Input: the small_house pair of tests/merging/data/small_house_flip (early_1, early_2: two drones'
maps of the same house). Goal: ready in <= 0.5 s.
Usage: scripts/bench merge_startup [--repeat N]. JSON in out/bench/merge_startup.json.
"""

import argparse
import json
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
PAIR = ROOT / "tests" / "merging" / "data" / "small_house_flip"
GOAL_S = 0.5

CHILD = r"""
import json, sys, time
t0, c0 = time.monotonic(), time.process_time()
sys.path.insert(0, ROOT)
import coopd.cli.coopctl  # noqa: F401  (what the command line loads before it parses)
from coopd.io import load_map
from coopd.merging.offline import merge_grids
t1, c1 = time.monotonic(), time.process_time()
def merge():
    return merge_grids([load_map(PATH_A)[0], load_map(PATH_B)[0]])
first = merge()
t2, c2 = time.monotonic(), time.process_time()
merge()
t3, c3 = time.monotonic(), time.process_time()
print(json.dumps({"import_s": t1 - t0, "import_cpu_s": c1 - c0, "first_s": t2 - t1, "first_cpu_s": c2 - c1,
                  "warm_s": t3 - t2, "warm_cpu_s": c3 - c2, "started_cpu_s": c0}))
"""


def run(code: str) -> tuple[float, str]:
    """(wall seconds from spawn to exit, stdout) of a fresh interpreter running code."""
    t = time.monotonic()
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    return time.monotonic() - t, out


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--repeat", type=int, default=5)
    a = p.parse_args()
    code = CHILD.replace("ROOT", repr(str(ROOT))).replace("PATH_A", repr(str(PAIR / "early_1.cmap"))) \
        .replace("PATH_B", repr(str(PAIR / "early_2.cmap")))
    run(code)  # fill the kernel cache if this checkout has none yet: measured runs load, never compile
    runs, bare, peer = [], [], []
    for _ in range(a.repeat):
        bare.append(run("pass")[0])
        peer.append(run("import numpy")[0])
        wall, out = run(code)
        r = json.loads(out.splitlines()[-1])
        r["process_s"] = wall
        r["ready_s"] = bare[-1] + r["import_s"] + max(0.0, r["first_s"] - r["warm_s"])
        kernels_cpu = max(0.0, r["first_cpu_s"] - r["warm_cpu_s"])
        r["ready_cpu_s"] = r["started_cpu_s"] + r["import_cpu_s"] + kernels_cpu
        runs.append(r)

    def med(key):
        return round(statistics.median(r[key] for r in runs), 3)

    result = {
        "benchmark": "merge_startup", "repeat": a.repeat, "goal_s": GOAL_S,
        "ready_s": med("ready_s"), "ready_cpu_s": med("ready_cpu_s"),
        "within_goal": med("ready_s") <= GOAL_S,
        "interpreter_s": round(statistics.median(bare), 3),
        "peer_import_numpy_s": round(statistics.median(peer), 3),
        "ready_vs_peer": round(med("ready_s") / statistics.median(peer), 2),
        "import_s": med("import_s"), "import_cpu_s": med("import_cpu_s"),
        "kernel_loading_s": round(statistics.median(max(0.0, r["first_s"] - r["warm_s"]) for r in runs), 3),
        "warm_merge_s": med("warm_s"), "warm_merge_cpu_s": med("warm_cpu_s"),
        "whole_process_s": med("process_s"),
    }
    out = ROOT / "out" / "bench"
    out.mkdir(parents=True, exist_ok=True)
    (out / "merge_startup.json").write_text(json.dumps(result, indent=1) + "\n")
    print(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""How long a fresh `coopctl map merge` process takes before it does any merging work.

A fresh interpreter (as coopctl is) imports coopctl's merge path, then merges one real pair twice:
the first merge also loads every numba kernel it meets from the on-disk cache (or compiles it), the
second runs warm. Ready = interpreter start + imports + (first merge - second merge). The peers in
the same run: a bare interpreter that imports numpy (what any numerical Python tool pays), and
numba's floor, a process that imports numba and calls one trivial kernel from numba's cache (what
any tool with numba kernels pays). Wall and CPU (the child's process time) per phase, median of
--repeat fresh processes.

--python runs them with another interpreter, such as the drone install that `scripts/bench
install_size --keep DIR` leaves (DIR/bin/python: its own coopd and no SciPy); by default, this
checkout with the development venv (where SciPy is installed, and numba imports it at its first call).

Input: the small_house pair of tests/merging/data/small_house_flip (early_1, early_2: two drones'
maps of the same house). Goal: ready in <= 0.5 s.
Usage: scripts/bench merge_startup [--repeat N] [--python PATH]. JSON in out/bench/merge_startup.json.
"""

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
PAIR = ROOT / "tests" / "merging" / "data" / "small_house_flip"
GOAL_S = 0.5

CHILD = r"""
import json, sys, time
t0, c0 = time.monotonic(), time.process_time()
if ROOT:
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

TRIVIAL_KERNEL = """import numba
@numba.njit(cache=True)
def f(x):
    return x + 1
"""
NUMBA_FLOOR = ("import time; t = time.monotonic(); import trivial_kernel; trivial_kernel.f(1); "
               "print(time.monotonic() - t)")
"""numba's floor, timed as the merge is: from the first statement to the kernel's first result."""


def run(python: str, code: str) -> tuple[float, str]:
    """(wall seconds from spawn to exit, stdout) of a fresh interpreter running code (-I: neither
    PYTHONPATH nor the current directory puts another coopd on the path)."""
    t = time.monotonic()
    out = subprocess.run([python, "-I", "-c", code], capture_output=True, text=True, check=True).stdout
    return time.monotonic() - t, out


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--repeat", type=int, default=5)
    p.add_argument("--python", help="interpreter to measure (default: this one, with this checkout's coopd)")
    a = p.parse_args()
    python = a.python or sys.executable
    code = CHILD.replace("ROOT", repr("" if a.python else str(ROOT))) \
        .replace("PATH_A", repr(str(PAIR / "early_1.cmap"))) \
        .replace("PATH_B", repr(str(PAIR / "early_2.cmap")))
    runs, bare, peer, floor = [], [], [], []
    with tempfile.TemporaryDirectory() as kernel_dir:
        Path(kernel_dir, "trivial_kernel.py").write_text(TRIVIAL_KERNEL)
        floor_code = f"import sys; sys.path.insert(0, {kernel_dir!r}); {NUMBA_FLOOR}"
        run(python, code)  # fill the kernel caches if there are none yet: measured runs load, never compile
        run(python, floor_code)
        for _ in range(a.repeat):
            bare.append(run(python, "pass")[0])
            peer.append(run(python, "import numpy")[0])
            floor.append(bare[-1] + float(run(python, floor_code)[1]))
            wall, out = run(python, code)
            r = json.loads(out.splitlines()[-1])
            r["process_s"] = wall
            r["ready_s"] = bare[-1] + r["import_s"] + max(0.0, r["first_s"] - r["warm_s"])
            kernels_cpu = max(0.0, r["first_cpu_s"] - r["warm_cpu_s"])
            r["ready_cpu_s"] = r["started_cpu_s"] + r["import_cpu_s"] + kernels_cpu
            runs.append(r)

    def med(key):
        return round(statistics.median(r[key] for r in runs), 3)

    result = {
        "benchmark": "merge_startup", "repeat": a.repeat, "goal_s": GOAL_S, "python": python,
        "scipy_installed": run(python, "import importlib.util as u; print(bool(u.find_spec('scipy')))")[1]
        .strip() == "True",
        "ready_s": med("ready_s"), "ready_cpu_s": med("ready_cpu_s"),
        "within_goal": med("ready_s") <= GOAL_S,
        "interpreter_s": round(statistics.median(bare), 3),
        "peer_import_numpy_s": round(statistics.median(peer), 3),
        "ready_vs_peer": round(med("ready_s") / statistics.median(peer), 2),
        "numba_floor_s": round(statistics.median(floor), 3),
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

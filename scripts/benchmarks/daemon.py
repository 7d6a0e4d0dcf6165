"""scripts/bench daemon: mapping latency inside the running daemon, with and without a merge.

coopd's Daemon (in this process, all its threads and priorities) maps from coopd-sim (a
subprocess: one vehicle flying the built-in route, 160x120 depth at 10 Hz of simulated time,
real MAVLink and camera socket). Latency is frame arrival (last byte read from the camera
socket) -> local grid updated. Phases:
  idle     mapping only;
  merging  the merging thread (nice +10) runs coopd.merging.merge_all back to back on the local
           map and a received map (the local map of this flight as vehicle 2, i.e. a real map of
           the same size and content), while mapping goes on.
Also frames in / mapped / dropped (newest-wins replacements) / skipped, RSS (sampled every 0.1 s)
against the memory budget. Goal (issue 6): p99 <= 100 ms, zero drops while a merge runs.
Prints JSON and writes out/bench/daemon.json.
"""

import argparse
import json
import os
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path[:0] = [str(ROOT)]

from coopd.daemon.config import from_dict  # noqa: E402
from coopd.daemon.service import Daemon  # noqa: E402
from coopd.sharing.wire import MapMeta, encode_map  # noqa: E402


def start_sim(workdir: Path, port: int, speed: float, world: str):
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    proc = subprocess.Popen(
        [sys.executable, "-m", "firmware_sim.cli", "--world", world, "--speed", str(speed), "--route",
         "builtin", "--mavlink-port", str(port), "--camera-dir", str(workdir / "cam"), "--duration", "3600",
         "--gcs-port", "0"],
        stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, env=env, cwd=ROOT)
    info = json.loads(proc.stdout.readline())
    return proc, info


def phase(daemon: Daemon, seconds: float, merging: bool) -> dict:
    """Run one measured phase; returns its figures."""
    cam0 = dict(daemon.camera.counters)
    drops0, mapped0 = daemon.slot.dropped, daemon.frames_mapped
    skipped0 = sum(daemon.associator.skipped.values())
    merges0 = dict(daemon.merger.counters)
    daemon.latency_s.clear()
    rss = []
    merges, seen = [], daemon.merger.last
    t_end = time.monotonic() + seconds
    while time.monotonic() < t_end:
        last = daemon.merger.last
        if last is not seen and last is not None:
            merges.append(last)
            seen = last
        if merging and daemon.merger.busy_since is None:
            daemon.merger.request("bench")  # back to back: a merge is running nearly all the time
        rss.append(daemon.budget.rss())
        time.sleep(0.1)
    lat = np.array(daemon.latency_s) * 1e3
    done = {k: daemon.merger.counters[k] - merges0[k] for k in merges0}
    return {
        "seconds": seconds,
        "frames_in": daemon.camera.counters["frames"] - cam0.get("frames", 0),
        "frames_mapped": daemon.frames_mapped - mapped0,
        "frames_dropped": daemon.slot.dropped - drops0,
        "frames_skipped": sum(daemon.associator.skipped.values()) - skipped0,
        "latency_ms": {
            "n": int(lat.size),
            "p50": round(float(np.percentile(lat, 50)), 2) if lat.size else None,
            "p99": round(float(np.percentile(lat, 99)), 2) if lat.size else None,
            "max": round(float(lat.max()), 2) if lat.size else None,
        },
        "merges": done,
        "merge_seconds": [m["seconds"] for m in merges],
        "last_merge": daemon.merger.last if merging else None,
        "rss_mib": {"max": round(max(rss) / 2**20, 1), "mean": round(float(np.mean(rss)) / 2**20, 1)},
    }


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=20.0, help="wall seconds per measured phase")
    ap.add_argument("--warmup", type=float, default=15.0, help="wall seconds of mapping before measuring")
    ap.add_argument("--speed", type=float, default=1.0, help="sim speed (1.0: 10 frames/s as on a drone)")
    ap.add_argument("--world", default="small_house")
    ap.add_argument("--memory-mb", type=int, default=512)
    ap.add_argument("--port", type=int, default=15390)
    args = ap.parse_args()

    work = Path(tempfile.mkdtemp(prefix="coopd-bench-", dir="/tmp"))
    (work / "cam").mkdir()
    config = from_dict({
        "vehicle": {"id": 1, "mavlink": f"udpin:127.0.0.1:{args.port}"},
        "camera": {"source": f"socket:{work / 'cam' / 'camera0.sock'}"},
        "sharing": {"enabled": False},
        "merging": {"period_s": 86400.0, "on_receive": False},
        "daemon": {"memory_mb": args.memory_mb, "state_dir": str(work / "state"),
                   "control_socket": str(work / "control.sock"), "checkpoint_period_s": 0.0},
    })
    daemon = Daemon(config)
    daemon.start()
    runner = threading.Thread(target=daemon.run, name="bench-main-loop", daemon=True)
    runner.start()
    sim, info = start_sim(work, args.port, args.speed, args.world)
    try:
        t0 = time.monotonic()
        while daemon.frames_mapped < 10 and time.monotonic() - t0 < 60:
            time.sleep(0.2)
        time.sleep(args.warmup)
        idle = phase(daemon, args.seconds, merging=False)
        grid, version = daemon.known_snapshot()
        received = SimpleNamespace(vehicle_id=2, version=version, data=encode_map(grid, MapMeta(2, version)))
        merger = daemon.merger
        merger.sources = replace(merger.sources, received_maps=lambda: [received])
        merger.settings = replace(merger.settings, min_gap_s=0.0)  # back to back, the worst case for mapping
        merging = phase(daemon, args.seconds, merging=True)
        status = daemon.handle_status({})
    finally:
        sim.terminate()
        sim.wait(10)
        daemon.request_stop("bench done")
        runner.join(5)
        daemon.shutdown()
    goal = {"p99_ms_max": 100.0, "drops_while_merging": 0}
    result = {
        "bench": "daemon",
        "conditions": {"world": args.world, "sim_speed": args.speed, "camera": "160x120 @ 10 Hz sim time",
                       "frames_per_wall_s": 10 * args.speed, "cpus": os.cpu_count(),
                       "load_avg_1min": os.getloadavg()[0], "memory_budget_mib": args.memory_mb,
                       "merge_fn": "coopd.merging.merge_all" if daemon.merger.available else None,
                       "received_map": f"this flight's local map as vehicle 2, {len(received.data)} bytes, "
                                       f"{'x'.join(map(str, grid.shape))} cells"},
        "idle": idle,
        "merging": merging,
        "map": status["map"],
        "threads": [{k: t[k] for k in ("role", "thread", "requested", "applied")} for t in status["threads"]],
        "memory": {k: status["memory"][k] for k in ("budget_bytes", "baseline_bytes", "peak_reserved_bytes",
                                                     "peak_rss_bytes", "rss_over_budget", "refused")},
        "goal": goal,
        "goal_met": {
            "p99_idle": (idle["latency_ms"]["p99"] or 1e9) <= goal["p99_ms_max"],
            "p99_merging": (merging["latency_ms"]["p99"] or 1e9) <= goal["p99_ms_max"],
            "zero_drops_merging": merging["frames_dropped"] == 0,
            "merges_ran": merging["merges"]["done"] + merging["merges"]["failed"] > 0,
            "rss_under_budget": status["memory"]["peak_rss_bytes"] <= status["memory"]["budget_bytes"],
        },
    }
    out = ROOT / "out" / "bench"
    out.mkdir(parents=True, exist_ok=True)
    (out / "daemon.json").write_text(json.dumps(result, indent=2))
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()

"""The demo: firmware_sim flies a few drones through a world, one coopd daemon per drone maps,
shares and merges; then a report and the merged maps (out/global_<id>.png and .cmap).

Run through scripts/demo, which sets up .venv first. Every process this starts is stopped on
exit, Ctrl-C included.
"""

import argparse
import json
import math
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from coopd.daemon import control  # noqa: E402
from coopd.geometry import invert  # noqa: E402
from coopd.io import export_png_top, load_cmap  # noqa: E402
from coopd.io.atomic import write_atomic  # noqa: E402
from coopd.sharing.wire import decode_map  # noqa: E402
from firmware_sim import accuracy as acc  # noqa: E402
from firmware_sim.simulation import Simulation  # noqa: E402
from firmware_sim.worlds import GENERATORS, build_world  # noqa: E402

MAVLINK_BASE = 14740
SHARING_BASE = 17400


def parse_args():
    p = argparse.ArgumentParser(prog="scripts/demo", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--world", choices=sorted(GENERATORS), default="small_house")
    p.add_argument("--drones", type=int, default=3, help="number of drones (1..10)")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--speed", type=float, default=2.0, help="simulated seconds per wall second")
    p.add_argument("--timeout", type=float, default=270.0, help="wall seconds before giving up")
    p.add_argument("--out", type=Path, default=ROOT / "out")
    p.add_argument("--keep", action="store_true", help="keep the temporary directory (configs, logs)")
    a = p.parse_args()
    if not 1 <= a.drones <= 10:
        p.error("--drones must be within 1..10")
    return a


def daemon_config(i: int, n: int, tmp: Path) -> str:
    """The coopd.toml of drone i: its own MAVLink port, camera socket, map server and state."""
    peers = ", ".join(f'"127.0.0.1:{SHARING_BASE + j}"' for j in range(n) if j != i)
    return f"""
[vehicle]
id = {i + 1}
mavlink = "udpin:127.0.0.1:{MAVLINK_BASE + i}"

[camera]
source = "socket:{tmp / f'camera{i}.sock'}"

[sharing]
listen_host = "127.0.0.1"
port = {SHARING_BASE + i}
peers = [{peers}]
scan_period_s = 1.0

[merging]
period_s = 5.0

[daemon]
memory_mb = 768
state_dir = "{tmp / f'state{i}'}"
control_socket = "{tmp / f'control{i}.sock'}"
checkpoint_period_s = 30.0
"""


class Demo:
    """Owns the simulation and the daemons; stop() tears everything down."""

    def __init__(self, args):
        self.args = args
        self.tmp = Path(tempfile.mkdtemp(prefix="coopd-demo-"))
        self.daemons: list[subprocess.Popen] = []
        self.sim: Simulation | None = None

    def socket(self, i: int) -> Path:
        return self.tmp / f"control{i}.sock"

    def start(self):
        """The simulation (vehicles idle on the ground, streaming MAVLink and camera frames), then
        the daemons: the first alone, so it fills numba's kernel cache the others then load."""
        a = self.args
        world = build_world(a.world, a.seed)
        print(f"demo: world {a.world} (seed {a.seed}), {a.drones} drones, "
              f"firmware_sim at {a.speed:g}x real time")
        self.world = world
        self.sim = Simulation(world, a.drones, seed=a.seed, speed=a.speed, mavlink_base_port=MAVLINK_BASE,
                              camera_dir=str(self.tmp))
        self.sim.start()
        self.start_daemon(0)
        self.wait_ready([0], "compiling kernels (once; later starts load them from the cache)")
        for i in range(1, a.drones):
            self.start_daemon(i)
        self.wait_ready(range(a.drones), "starting the other daemons")
        print(f"demo: {a.drones} coopd daemons mapping (logs and configs in {self.tmp})")

    def start_daemon(self, i: int) -> None:
        cfg = self.tmp / f"coopd{i}.toml"
        cfg.write_text(daemon_config(i, self.args.drones, self.tmp))
        env = dict(os.environ, PYTHONPATH=str(ROOT))
        with open(self.tmp / f"coopd{i}.log", "wb") as log:
            cmd = [sys.executable, "-m", "coopd.daemon.main", "--config", str(cfg)]
            self.daemons.append(subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=env))

    def check_alive(self) -> None:
        for i, p in enumerate(self.daemons):
            if p.poll() is not None:
                raise RuntimeError(f"coopd of drone {i + 1} exited with code {p.returncode}; "
                                   f"see {self.tmp / f'coopd{i}.log'}")

    def wait_ready(self, drones, what: str, limit_s: float = 240.0) -> None:
        """Until every daemon in `drones` answers and maps (link up, frames arriving)."""
        t0 = time.monotonic()
        print(f"demo: {what} ...")
        while time.monotonic() - t0 < limit_s:
            self.check_alive()
            statuses = [self.status(i) for i in drones]
            if all(s and (s.get("mapping") or {}).get("state") == "mapping" for s in statuses):
                print(f"demo: ready after {time.monotonic() - t0:.0f} s")
                return
            time.sleep(1.0)
        raise RuntimeError(f"daemons not mapping after {limit_s:.0f} s; see the logs in {self.tmp}")

    def status(self, i: int) -> dict | None:
        try:
            return control.request(self.socket(i), "status", timeout_s=5.0)[0]
        except (control.ControlError, OSError):
            return None

    def stop(self):
        for p in self.daemons:
            if p.poll() is None:
                p.send_signal(signal.SIGTERM)
        deadline = time.monotonic() + 10
        for p in self.daemons:
            try:
                p.wait(timeout=max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
        if self.sim is not None:
            self.sim.stop()
        if not self.args.keep:
            shutil.rmtree(self.tmp, ignore_errors=True)


def summary(s: dict | None) -> str:
    if not s:
        return "starting"
    m, f, mg = s.get("map") or {}, s.get("frames") or {}, s.get("merges") or {}
    peers = s.get("peers") or []
    return (f"{(s.get('link') or {}).get('state', '?')}, {f.get('mapped', 0)} frames mapped, "
            f"{m.get('known', 0)} known cells, {len(peers)} peers, {mg.get('done', 0)} merges")


def progress_line(demo: Demo, t0: float, n: int) -> str:
    flying = [not demo.sim.route_finished(i) for i in range(n)]
    return (f"[{time.monotonic() - t0:5.0f} s, sim {demo.sim.time:5.0f} s] " + " | ".join(
        f"drone {i + 1}: {'flying' if flying[i] else 'landed'}, {summary(demo.status(i))}" for i in range(n)))


def merged_vehicles(s: dict | None) -> dict:
    """Vehicle id -> offset entry of every map merged into this daemon's global map."""
    if not s:
        return {}
    offsets = (s.get("merges") or {}).get("offsets") or {}
    return {int(k): v for k, v in offsets.items() if v.get("accepted", True)}


def world_from_map(sim: Simulation, i: int, link: dict) -> np.ndarray:
    """Truth: drone i's map frame in the world (its reporting frame as drifted when the daemon took
    its first sample, moved to that sample); `link` is the daemon's status["link"]."""
    return acc.map_frame_in_world(sim.vehicle(i).odometry, link.get("map_origin_fc_enu"),
                                  link.get("map_origin_t_fc"))


def map_vs_truth(demo: Demo, i: int, grid, truth_i: np.ndarray, link: dict) -> dict:
    """Occupied-cell precision/recall of a map of drone i vs the world's ground truth in the region it
    explored, and the drift the emulator put into drone i's odometry since its map origin."""
    gt, gt_origin = demo.world.ground_truth(0.1)
    out = acc.map_accuracy(grid, acc.transform_points(truth_i), gt, gt_origin)
    t0 = link.get("map_origin_t_fc")
    if t0 is not None:
        out["drift_m"], out["drift_deg"] = acc.drift_since(demo.sim.vehicle(i).odometry, t0, demo.sim.time)
    return {k: round(v, 4) if isinstance(v, float) else v for k, v in out.items()}


def main() -> int:
    args = parse_args()
    demo = Demo(args)
    interrupted = False

    def on_signal(*_):
        raise KeyboardInterrupt

    signal.signal(signal.SIGTERM, on_signal)
    t0 = time.monotonic()
    try:
        demo.start()
        n = args.drones
        demo.sim.fly_builtin_routes()
        print("demo: drones take off and fly their exploration routes")
        last_print = 0.0
        while any(not demo.sim.route_finished(i) for i in range(n)):
            if time.monotonic() - t0 > args.timeout:
                print("demo: time is up before every drone landed; reporting what there is")
                break
            time.sleep(1.0)
            demo.check_alive()
            if time.monotonic() - last_print >= 5.0:
                last_print = time.monotonic()
                print(progress_line(demo, t0, n))
        print("demo: every drone has landed; merging every map on every drone")
        merge_deadline = time.monotonic() + 90.0
        while time.monotonic() < merge_deadline and time.monotonic() - t0 < args.timeout + 60:
            for i in range(n):
                try:
                    control.request(demo.socket(i), "merge-now", timeout_s=120.0)
                except control.ControlError as e:
                    print(f"demo: merge-now on drone {i + 1}: {e}")
            print(progress_line(demo, t0, n))
            if all(len(merged_vehicles(demo.status(i))) >= n - 1 for i in range(n)):
                break
            time.sleep(5.0)
        return report(demo, [demo.status(i) for i in range(n)], time.monotonic() - t0)
    except KeyboardInterrupt:
        interrupted = True
        print("\ndemo: interrupted; stopping every process")
        return 130
    finally:
        demo.stop()
        if interrupted:
            print("demo: stopped")


def report(demo: Demo, statuses, elapsed: float) -> int:
    args = demo.args
    out = args.out
    out.mkdir(parents=True, exist_ok=True)
    n = args.drones
    print(f"\n== coopd demo report: {args.world}, {n} drones, {elapsed:.0f} s wall, "
          f"{demo.sim.time:.0f} s simulated")
    links = [(s or {}).get("link") or {} for s in statuses]
    ok = True
    accuracy = []
    for i, s in enumerate(statuses):
        vid = i + 1
        if not s:
            print(f"drone {vid}: no status (daemon not answering)")
            ok = False
            continue
        m = s.get("map") or {}
        received = sum(1 for p in s.get("peers") or [] if p.get("map_version") is not None)
        merged = merged_vehicles(s)
        print(f"drone {vid}: {m.get('known', 0)} cells mapped, {received} maps received, "
              f"{(s.get('merges') or {}).get('done', 0)} merges, {len(merged)}/{n - 1} maps merged")
        truth_i = world_from_map(demo.sim, i, links[i])
        entry_i = {"drone": vid, "merged": len(merged), "pairs": []}
        accuracy.append(entry_i)
        for j in range(n):
            if j == i:
                continue
            entry = merged.get(j + 1)
            if entry is None:
                print(f"   drone {j + 1}: not merged")
                entry_i["pairs"].append({"peer": j + 1, "merged": False})
                ok = False
                continue
            est = np.array(entry["transform"], float).reshape(4, 4)
            truth = invert(truth_i) @ world_from_map(demo.sim, j, links[j])
            dt, dyaw = acc.offset_error(est, truth)
            entry_i["pairs"].append({"peer": j + 1, "merged": True, "error_m": round(dt, 4),
                                     "error_deg": round(dyaw, 3)})
            yaw = math.degrees(math.atan2(est[1, 0], est[0, 0]))
            print(f"   drone {j + 1}: offset x {est[0, 3]:6.2f} y {est[1, 3]:6.2f} z {est[2, 3]:5.2f} m, "
                  f"yaw {yaw:7.1f} deg; error vs truth {dt:.2f} m, {dyaw:.1f} deg")
        try:
            _, blob = control.request(demo.socket(i), "dump-map", {"map": "global"}, timeout_s=60.0,
                                      max_blob_bytes=512 * 1024 * 1024)
            cmap = out / f"global_{vid}.cmap"
            write_atomic(cmap, blob)
            grid, _ = load_cmap(cmap)
            export_png_top(grid, out / f"global_{vid}.png")
            print(f"   wrote {cmap} and {out / f'global_{vid}.png'}")
            entry_i["global"] = map_vs_truth(demo, i, grid, truth_i, links[i])
            _, blob = control.request(demo.socket(i), "dump-map", {"map": "local"}, timeout_s=60.0,
                                      max_blob_bytes=512 * 1024 * 1024)
            entry_i["local"] = map_vs_truth(demo, i, decode_map(blob)[0], truth_i, links[i])
            g, loc = entry_i["global"], entry_i["local"]
            print(f"   vs ground truth: global map precision {g['precision']:.3f} recall {g['recall']:.3f}; "
                  f"own map {loc['precision']:.3f} / {loc['recall']:.3f}; "
                  f"odometry drift since map origin {loc.get('drift_m', math.nan):.2f} m, "
                  f"{loc.get('drift_deg', math.nan):.2f} deg")
        except (control.ControlError, OSError, ValueError) as e:
            print(f"   could not dump the global map: {e}")
            ok = False
    report_json = {"world": args.world, "drones": n, "elapsed_s": elapsed, "sim_s": demo.sim.time,
                "lag_resets": demo.sim.lag_resets, "accuracy": accuracy, "statuses": statuses}
    (out / "demo_report.json").write_text(json.dumps(report_json, indent=1, default=str))
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())

"""The demo: firmware_sim flies a few drones through a world, one coopd daemon per drone maps,
shares and merges; then a report and the merged maps (out/global_<id>.png and .cmap).

Run through scripts/demo, which sets up .venv first. Every process this starts is stopped on
exit, Ctrl-C included.
"""

import argparse
import json
import math
import signal
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from coopd.daemon import control  # noqa: E402
from coopd.io import export_png_top, load_cmap  # noqa: E402
from coopd.io.atomic import write_atomic  # noqa: E402
from coopd.io.png import map_title  # noqa: E402
from coopd.sharing.wire import decode_map  # noqa: E402
from firmware_sim.swarm import Swarm, SwarmSettings  # noqa: E402
from firmware_sim.worlds import GENERATORS, world_name  # noqa: E402


def parse_args():
    p = argparse.ArgumentParser(prog="scripts/demo", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--world", type=world_name, default="small_house",
                   help=f"one of {', '.join(sorted(GENERATORS))}, or gen:SEED[:key=value,...] (generated)")
    p.add_argument("--autopilot", choices=("px4", "ardupilot"), default="px4",
                   help="the flight controllers' MAVLink personality (ardupilot: ArduCopter)")
    p.add_argument("--drones", type=int, default=3, help="number of drones (1..10)")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--speed", type=float, default=2.0, help="simulated seconds per wall second")
    p.add_argument("--network", choices=("auto", "netns", "loopback"), default="auto",
                   help="one network namespace per drone (auto: when root with iproute2) or loopback")
    p.add_argument("--port-base", type=int, default=SwarmSettings.mavlink_base,
                   help="MAVLink UDP ports from here (one per drone); map servers on port-base + 2660")
    p.add_argument("--timeout", type=float, default=270.0, help="wall seconds before giving up")
    p.add_argument("--out", type=Path, default=ROOT / "out")
    p.add_argument("--keep", action="store_true", help="keep the work directory (configs, logs)")
    p.add_argument("--record", action="store_true",
                   help="every daemon records its flight to OUT/recordings/coopd-vehicle<ID>-<time>.mcap "
                        "(pose, track, map updates, peers' frames, status; opens in the Foxglove app)")
    p.add_argument("--viewer", nargs="?", type=int, const=8765, default=0, metavar="PORT",
                   help="every daemon serves its live view (Foxglove WebSocket, default port 8765) on its "
                        "swarm address; the URLs are printed at start (open them in the Foxglove app)")
    a = p.parse_args()
    if not 1 <= a.drones <= 10:
        p.error("--drones must be within 1..10")
    return a


def demo_config(args, recordings: Path) -> dict:
    """coopd.toml sections every drone's daemon gets on top of the swarm's: each sends its flight
    controller OBSTACLE_DISTANCE from its global map; with --record, a recording of the flight."""
    config = {"obstacles": {"enabled": True}}
    if args.record:
        config["viewer"] = {"record_dir": str(recordings)}
    return config


def obstacles_line(status: dict, fc_received: int | None) -> str:
    """The report's OBSTACLE_DISTANCE line of one drone: what its daemon had sent at its last status,
    what its FC has received by the time of the report."""
    ob = status.get("obstacles") or {}
    if not ob.get("sending") and not ob.get("sent"):
        return f"obstacles: not sent (FC: {ob.get('fc', '-')})"
    nearest = ob.get("nearest_m")
    return (f"obstacles: {ob.get('sent', 0)} OBSTACLE_DISTANCE sent at {ob.get('rate_hz')} Hz "
            f"({ob.get('with_global', 0)} with the global map, {ob.get('no_pose', 0)} without a pose), "
            f"last nearest {'-' if nearest is None else f'{nearest} m'}; the FC has received "
            f"{'-' if fc_received is None else fc_received} by now (the daemon kept sending)")


def summary(s: dict | None) -> str:
    if not s:
        return "starting"
    m, f, mg = s.get("map") or {}, s.get("frames") or {}, s.get("merges") or {}
    peers = s.get("peers") or []
    return (f"{(s.get('link') or {}).get('state', '?')}, {f.get('mapped', 0)} frames mapped, "
            f"{m.get('known', 0)} known cells, {len(peers)} peers, {mg.get('done', 0)} merges")


def progress_line(swarm: Swarm, t0: float) -> str:
    n = swarm.settings.drones
    states = ["flying" if not swarm.sim.route_finished(i) else "landed" for i in range(n)]
    return (f"[{time.monotonic() - t0:5.0f} s, sim {swarm.sim.time:5.0f} s] " + " | ".join(
        f"drone {i + 1}: {states[i]}, {summary(swarm.status(i))}" for i in range(n)))


def main() -> int:
    args = parse_args()
    recordings, started_at = (args.out / "recordings").resolve(), time.time()
    swarm = Swarm(SwarmSettings(world=args.world, drones=args.drones, seed=args.seed, speed=args.speed,
                                network=args.network, mavlink_base=args.port_base,
                                sharing_port=args.port_base + 2660, autopilot=args.autopilot,
                                viewer_port=args.viewer, config=demo_config(args, recordings)))
    interrupted = False

    def on_signal(*_):
        raise KeyboardInterrupt

    signal.signal(signal.SIGTERM, on_signal)
    t0 = time.monotonic()
    try:
        n = args.drones
        print(f"demo: world {args.world} (seed {args.seed}), {n} drones ({args.autopilot}), "
              f"firmware_sim at {args.speed:g}x real time")
        swarm.start()
        print(f"demo: {n} coopd daemons mapping, network: {swarm.network_mode} "
              f"({', '.join(swarm.address(i) for i in range(n))}); files in {swarm.workdir}")
        if args.viewer:
            print("demo: live views (Foxglove app: Open connection, Foxglove WebSocket): "
                  + ", ".join(f"drone {i + 1} {swarm.viewer_url(i)}" for i in range(n)))
        swarm.fly()
        print("demo: drones take off and fly their exploration routes")
        last_print = 0.0
        while not swarm.landed():
            if time.monotonic() - t0 > args.timeout:
                print("demo: time is up before every drone landed; reporting what there is")
                break
            time.sleep(1.0)
            swarm.check_alive()
            if time.monotonic() - last_print >= 5.0:
                last_print = time.monotonic()
                print(progress_line(swarm, t0))
        print("demo: every drone has landed; merging every map on every drone")
        if not swarm.merge_until_converged(limit_s=max(30.0, args.timeout + 60 - (time.monotonic() - t0)),
                                           progress=lambda: print(progress_line(swarm, t0))):
            print("demo: time is up before every daemon merged every map; reporting what there is")
        return report(swarm, args, swarm.statuses(), time.monotonic() - t0)
    except KeyboardInterrupt:
        interrupted = True
        print("\ndemo: interrupted; stopping every process")
        return 130
    finally:
        swarm.stop(keep_files=args.keep)  # the daemons close their recordings as they stop
        if args.record:
            files = [str(f) for f in sorted(recordings.glob("*.mcap")) if f.stat().st_mtime >= started_at]
            print(f"demo: recordings (open in the Foxglove app): {', '.join(files) or 'none'}")
        if interrupted:
            print("demo: stopped; every process and namespace it made is gone")


def save_flight(swarm: Swarm, i: int, status: dict, path: Path) -> None:
    """What scoring the maps needs after the run: the drone's true trajectory, its camera, its map
    frame in the world and the drones whose maps its global map holds (scripts/bench accuracy)."""
    cam = swarm.sim.vehicles[i].camera.cfg
    members = [i + 1] + sorted(swarm.merged_vehicles(status))
    np.savez(path, trajectory=swarm.sim.trajectory(i), world_from_map=swarm.map_to_world(i, status),
             members=np.array(members), camera=np.array(
                 [cam.width, cam.height, cam.hfov_deg, cam.rate_hz, cam.tilt_down_deg, *cam.offset_body]))


def report(swarm: Swarm, args, statuses, elapsed: float) -> int:
    """Print what happened per drone, dump every global map to out/, write out/demo_report.json."""
    out = args.out
    out.mkdir(parents=True, exist_ok=True)
    n = args.drones
    print(f"\n== coopd demo report: {args.world}, {n} drones, {elapsed:.0f} s wall, "
          f"{swarm.sim.time:.0f} s simulated, network {swarm.network_mode}")
    ok = True
    drones = []
    for i, s in enumerate(statuses):
        vid = i + 1
        if not s:
            print(f"drone {vid}: no status (daemon not answering)")
            ok = False
            continue
        m = s.get("map") or {}
        received = sum(1 for p in s.get("peers") or [] if p.get("map_version") is not None)
        errors = swarm.offset_errors(i, statuses)
        print(f"drone {vid}: {m.get('known', 0)} cells mapped, {received} maps received, "
              f"{(s.get('merges') or {}).get('done', 0)} merges, {len(errors)}/{n - 1} maps merged")
        link = swarm.sim.vehicles[i].link
        fc_received = None if link is None else link.stats.get("obstacle_distance")
        print(f"   {obstacles_line(s, fc_received)}")
        for j in range(n):
            if j == i:
                continue
            e = errors.get(j + 1)
            if e is None:
                print(f"   drone {j + 1}: not merged")
                ok = False
                continue
            x, y, z = e["translation_m"]
            print(f"   drone {j + 1}: offset x {x:6.2f} y {y:6.2f} z {z:5.2f} m, "
                  f"yaw {e['yaw_deg']:7.1f} deg; "
                  f"error vs truth {e['error_m']:.2f} m, {e['error_deg']:.1f} deg")
        entry = {"drone": vid, "merged": len(errors), "pairs": [
            {"peer": j + 1, "merged": j + 1 in errors,
             **({k: round(errors[j + 1][k], 4) for k in ("error_m", "error_deg")} if j + 1 in errors else {})}
            for j in range(n) if j != i], "obstacle_distance_fc_received": fc_received}
        drones.append(entry)
        try:
            _, blob = swarm.daemons[i].request("dump-map", {"map": "global"}, timeout_s=60.0,
                                               max_blob_bytes=512 * 1024 * 1024)
            cmap = out / f"global_{vid}.cmap"
            write_atomic(cmap, blob)
            grid, meta = load_cmap(cmap)
            tracks, left_out = swarm.tracks_in_map(i, statuses)
            export_png_top(grid, out / f"global_{vid}.png", title=map_title(grid.resolution, vid, meta.stamp),
                           tracks=tracks, notes=[f"drone {j}: not merged into this map, track not drawn"
                                                 for j in left_out])
            print(f"   wrote {cmap} and {out / f'global_{vid}.png'}")
            entry["global"] = g = swarm.map_accuracy(i, grid, s)
            _, blob = swarm.daemons[i].request("dump-map", {"map": "local"}, timeout_s=60.0,
                                               max_blob_bytes=512 * 1024 * 1024)
            write_atomic(out / f"local_{vid}.cmap", blob)
            entry["local"] = own = swarm.map_accuracy(i, decode_map(blob)[0], s)
            save_flight(swarm, i, s, out / f"flight_{vid}.npz")
            print(f"   vs ground truth: global map precision {g['precision']:.3f} recall {g['recall']:.3f} "
                  f"(within one cell {g['precision_tol1']:.3f} / {g['recall_tol1']:.3f}); own map "
                  f"{own['precision']:.3f} / {own['recall']:.3f}; odometry drift since the map origin "
                  f"{own.get('drift_m', math.nan):.2f} m, {own.get('drift_deg', math.nan):.2f} deg")
        except (control.ControlError, OSError, ValueError) as e:
            print(f"   could not dump the global map: {e}")
            ok = False
    (out / "demo_report.json").write_text(json.dumps(
        {"world": args.world, "autopilot": args.autopilot, "drones": n, "network": swarm.network_mode,
         "elapsed_s": elapsed,
         "sim_s": swarm.sim.time, "lag_resets": swarm.sim.lag_resets, "accuracy": drones,
         "statuses": statuses}, indent=1, default=str))
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())

"""coopd-sim: run N emulated quadrotors (PX4 or ArduCopter personality) with depth cameras in a generated
world. Each vehicle has an onboard/API MAVLink instance (sends to 127.0.0.1:14540+i) and a GCS instance
(sends to 127.0.0.1:14550), as PX4 SITL has."""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import signal
import sys
import tempfile
import threading
import time

from coopd.version import add_version_option
from firmware_sim.camera import CameraConfig
from firmware_sim.simulation import Simulation
from firmware_sim.worlds import GENERATORS, build_world, world_name


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    """Command-line options."""
    p = argparse.ArgumentParser(prog="coopd-sim", description=__doc__)
    add_version_option(p)
    p.add_argument("--world", type=world_name, default="small_house",
                   help=f"one of {', '.join(sorted(GENERATORS))}, or gen:SEED[:key=value,...] (generated)")
    p.add_argument("--size", type=float, default=None, help="scale on the world's default extent (0.5..4)")
    p.add_argument("--vehicles", type=int, default=1)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--speed", type=float, default=1.0, help="simulated seconds per wall second")
    p.add_argument(
        "--route",
        choices=["builtin", "none"],
        default="none",
        help="builtin: every vehicle arms and flies the world's exploration route",
    )
    p.add_argument("--noise", choices=["none", "default", "high"], default="default")
    p.add_argument(
        "--frame",
        choices=["start", "world"],
        default="start",
        help="odometry frame: each vehicle's start pose (default) or the shared world frame",
    )
    p.add_argument("--autopilot", choices=["px4", "ardupilot"], default="px4",
                   help="MAVLink personality: PX4, or ArduCopter (modes, streams, parameter names)")
    p.add_argument("--mavlink-port", type=int, default=14540,
                   help="onboard/API instance: vehicle i sends to 127.0.0.1:PORT+i")
    p.add_argument("--gcs-port", type=int, default=14550,
                   help="GCS instance: every vehicle sends to 127.0.0.1:PORT (0: no GCS instance)")
    p.add_argument(
        "--camera-dir",
        default=None,
        help="directory for camera<i>.sock Unix sockets (default: a fresh temporary directory)",
    )
    p.add_argument(
        "--camera-tcp-port", type=int, default=None, help="also serve camera i on 127.0.0.1:PORT+i"
    )
    p.add_argument("--no-camera", action="store_true")
    p.add_argument("--camera-res", default="160x120", help="WxH")
    p.add_argument("--camera-hfov", type=float, default=87.0)
    p.add_argument("--camera-rate", type=float, default=10.0)
    p.add_argument("--camera-range", default="0.2:5.0", help="MIN:MAX metres")
    p.add_argument("--camera-noise", type=float, default=0.0, help="range sigma at 1 m (grows with z^2)")
    p.add_argument("--camera-dropout", type=float, default=0.0)
    p.add_argument(
        "--start-poses",
        default=None,
        help="'x,y,yaw_deg;x,y,yaw_deg;...' world-frame start poses, one per vehicle "
        "(default: the world's suggestions)",
    )
    p.add_argument("--duration", type=float, default=None, help="stop after this many simulated seconds")
    return p.parse_args(argv)


def camera_config(a: argparse.Namespace) -> CameraConfig | None:
    """Build the camera settings from the options."""
    if a.no_camera:
        return None
    w, h = (int(x) for x in a.camera_res.lower().split("x"))
    lo, hi = (float(x) for x in a.camera_range.split(":"))
    cfg = CameraConfig(
        width=w,
        height=h,
        hfov_deg=a.camera_hfov,
        rate_hz=a.camera_rate,
        min_m=lo,
        max_m=hi,
        noise_sigma_m=a.camera_noise,
        dropout=a.camera_dropout,
    )
    cfg.validate()
    return cfg


def parse_start_poses(text: str | None) -> list[tuple[float, float, float, float]] | None:
    """Parse 'x,y,yaw_deg;...' into (x, y, 0, yaw_rad) poses."""
    if text is None:
        return None
    poses = []
    for part in text.split(";"):
        x, y, yaw = (float(v) for v in part.split(","))
        if not all(math.isfinite(v) for v in (x, y, yaw)):
            raise ValueError(f"start pose {part!r} is not finite")
        poses.append((x, y, 0.0, math.radians(yaw)))
    return poses


def main(argv: list[str] | None = None) -> int:
    """Start the simulation, print the endpoints as JSON, run until SIGINT/SIGTERM or --duration."""
    a = parse_args(argv)
    try:
        cam = camera_config(a)
        world = build_world(a.world, a.seed, a.size)
        poses = parse_start_poses(a.start_poses)
        own_dir = None
        if a.camera_dir is None and cam is not None:
            own_dir = a.camera_dir = tempfile.mkdtemp(prefix="coopd-sim-")
        sim = Simulation(
            world,
            a.vehicles,
            seed=a.seed,
            speed=a.speed,
            noise=a.noise,
            camera=cam,
            frame=a.frame,
            start_poses=poses,
            mavlink_base_port=a.mavlink_port,
            gcs_port=a.gcs_port or None,
            autopilot=a.autopilot,
            camera_dir=a.camera_dir,
            camera_tcp_base_port=a.camera_tcp_port,
            route="builtin" if a.route == "builtin" else None,
        )
    except (ValueError, OSError) as e:
        print(f"coopd-sim: {e}", file=sys.stderr)
        return 2
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    print(
        json.dumps({"world": a.world, "seed": a.seed, "speed": a.speed, "vehicles": sim.endpoints()}),
        flush=True,
    )
    sim.start()
    wall0 = time.monotonic()
    try:
        while not stop.is_set():
            if a.duration is not None and sim.time >= a.duration:
                break
            stop.wait(0.2)
    finally:
        sim.stop()
        if own_dir is not None:
            with contextlib.suppress(OSError):
                os.rmdir(own_dir)
    wall = time.monotonic() - wall0
    stats = {
        "sim_time_s": round(sim.time, 3),
        "wall_s": round(wall, 3),
        "real_time_factor": round(sim.time / wall, 3) if wall > 0 else None,
        "pacing_resets": sim.lag_resets,
        "mavlink": [dict(v.link.stats) if v.link else {} for v in sim.vehicles],
        "mavlink_gcs": [dict(v.gcs_link.stats) if v.gcs_link else {} for v in sim.vehicles],
        "camera_frames_dropped": [v.publisher.frames_dropped if v.publisher else 0 for v in sim.vehicles],
        "contacts": [v.contact_count for v in sim.vehicles],
    }
    print(json.dumps(stats), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())

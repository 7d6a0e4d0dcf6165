"""End to end: firmware_sim flies a built-in route; link + camera client + association feed the Mapper;
the map matches the world's ground truth in the vehicle's true start frame."""

import json
import os
import time

import numpy as np
import pytest
from sim_helpers import pose_errors, wait_until

from coopd.camera import SocketDepthSource, SocketSourceConfig
from coopd.mapping import Mapper, MapperConfig, load_kernels
from coopd.mapping.association import FrameAssociator
from coopd.vehicle import LinkConfig, VehicleLink
from firmware_sim.accuracy import map_accuracy
from firmware_sim.odometry import NOISE_PRESETS, NoiseConfig
from firmware_sim.simulation import Simulation
from firmware_sim.worlds import build_world

WALL_SECONDS = float(os.environ.get("COOPD_E2E_SECONDS", "25"))
# More cases for measurement runs, e.g. COOPD_E2E_CASES="maze:white,small_warehouse:default:ardupilot".
# The ArduPilot personality sends no ODOMETRY: coopd builds poses from LOCAL_POSITION_NED and the
# ATTITUDE_QUATERNION it asks for, within the same bounds.
CASES = [("small_house", "white", "px4"), ("small_house", "default", "px4"),
         ("small_house", "default", "ardupilot")] + [
    (*c.split(":")[:3], "px4")[:3] for c in os.environ.get("COOPD_E2E_CASES", "").split(",") if ":" in c
]
SPEED = 2.0
# The default preset without drift: white noise on every report only (drift makes the map itself drift).
WHITE = NoiseConfig(drift_xy_m_s=0.0, drift_z_m_s=0.0, drift_yaw_rad_s=0.0)


@pytest.mark.slow
@pytest.mark.parametrize("world_name, noise, autopilot", CASES)
def test_route_maps_the_world(world_name, noise, autopilot, tmp_path, udp_port):
    load_kernels()  # before the clock starts, as the daemon does at boot
    world = build_world(world_name, 0)
    sim = Simulation(
        world,
        1,
        seed=0,
        speed=SPEED,
        noise=NOISE_PRESETS[noise] if noise != "white" else WHITE,
        mavlink_base_port=udp_port,
        camera_dir=str(tmp_path),
        route="builtin",
        autopilot=autopilot,
    )
    link = VehicleLink(LinkConfig(connection=f"udpin:127.0.0.1:{udp_port}"))
    cam = SocketDepthSource(SocketSourceConfig(sim.vehicle(0).camera_path))
    mapper = Mapper(MapperConfig())
    assoc = FrameAssociator(link)
    link.start()
    cam.start()
    sim.start()
    integrate_s = []
    lag_max = 0.0
    try:
        assert wait_until(lambda: not link.odometry_stale(), 5.0)
        t0 = time.monotonic()
        while time.monotonic() - t0 < WALL_SECONDS and not sim.route_finished(0):
            lag_max = max(lag_max, sim.lag_s)
            frame = cam.slot.take(timeout=0.5)
            if frame is None:
                continue
            a = assoc.associate(frame)
            if a is None:
                continue
            t1 = time.perf_counter()
            mapper.integrate(a.depth, a.intrinsics, a.camera_pose, a.stamp)
            integrate_s.append(time.perf_counter() - t1)
    finally:
        sim.stop()
        cam.stop()
        link.stop()
    v = sim.vehicle(0)
    odo, origin = v.odometry, link.odometry.origin_enu

    def to_world(p_map):
        """Map frame -> the vehicle's (drift-free) odometry frame -> world, i.e. via its true start pose."""
        return (p_map + origin) @ odo.frame_rot.T + odo.origin

    gt, gt_origin = world.ground_truth(0.1)
    acc = map_accuracy(mapper.grid, to_world, gt, gt_origin)
    pos_err, att_err = pose_errors(link, sim)
    report = {
        "world": world_name,
        "noise": noise,
        "autopilot": autopilot,
        "fallback_samples": link.counters["fallback_samples"],
        "sim_seconds": round(sim.time, 1),
        "speed": SPEED,
        "frames_received": cam.counters["frames"],
        "frames_dropped_slot": cam.slot.dropped,
        "frames_integrated": len(integrate_s),
        "association_skipped": dict(assoc.skipped),
        "integrate_ms_median": round(1e3 * float(np.median(integrate_s)), 2),
        "pose_error_rms_m": round(float(np.sqrt(np.mean(pos_err**2))), 4),
        "pose_error_max_m": round(float(pos_err.max()), 4),
        "attitude_error_max_deg": round(float(att_err.max()), 3),
        "sim_lag_max_s": round(lag_max, 3),
        "clock_rate": round(link.clock.estimate().rate, 4),
        "clock_uncertainty_ms": round(1e3 * link.clock.estimate().uncertainty_s, 2),
        **{k: round(v, 4) if isinstance(v, float) else v for k, v in acc.items()},
    }
    print(json.dumps(report))
    assert len(integrate_s) >= 100
    assert acc["observed_truth_cells"] > 2000
    assert acc["precision"] >= 0.9 and acc["recall"] >= 0.9, report
    if autopilot == "ardupilot":  # the poses came from LOCAL_POSITION_NED + ATTITUDE_QUATERNION
        assert report["fallback_samples"] >= 100 and report["pose_error_rms_m"] < 0.05, report

"""End to end: a drone flies and maps, its FC reboots in flight with the estimator's origin moved;
mapping pauses, the new frame is re-anchored on the map when the views pin it down (or mapping stays
paused with the reason), and the map never gets a shifted copy.

Prints one JSON line per case: time from the reboot to mapping resumed, the correction's error vs the
emulator's truth, the map's precision before and after.
    python -m pytest tests/vehicle/test_fc_reboot_mapping.py -s -m slow
"""

import json
import time

import numpy as np
import pytest
from sim_helpers import wait_until

from coopd.camera import SocketDepthSource, SocketSourceConfig
from coopd.mapping import Mapper, MapperConfig, load_kernels
from coopd.mapping.association import FrameAssociator
from coopd.mapping.reanchor import FrameReanchor
from coopd.mapping.sensor import CameraMount
from coopd.vehicle import LinkConfig, VehicleLink
from firmware_sim.accuracy import map_accuracy, offset_error
from firmware_sim.frames import rot_z
from firmware_sim.odometry import NoiseConfig
from firmware_sim.simulation import Simulation
from firmware_sim.worlds import build_world

SPEED = 2.0
WHITE = NoiseConfig(drift_xy_m_s=0.0, drift_z_m_s=0.0, drift_yaw_rad_s=0.0)
"""White noise on every report, no drift: the map frame's truth is exact."""
REBOOT_AT_S, AFTER_S = 9.0, 30.0
"""Simulated seconds into the route (22 m through the house's four rooms, about 22 s) of the reboot,
and of mapping after it (at most: the route ends first)."""
WALL_CAP_S = 60.0


def map_to_world(odometry, t_sim: float, origin_enu) -> np.ndarray:
    """4x4: the map frame (the reporting frame in use at t_sim, shifted by the map origin) in the world."""
    origin, yaw = odometry.frame_at(t_sim)
    out = np.eye(4)
    out[:3, :3] = rot_z(yaw)
    out[:3, 3] = rot_z(yaw) @ origin_enu + origin
    return out


def fly_and_map(link, cam, assoc, mapper, reanchor, sim, until_sim_s: float) -> tuple[int, int]:
    """Map until the simulated time or the end of the route (bounded in wall time); frames skipped while
    the FC's frame is paused go to the re-anchoring. Returns (frames mapped, of them after coopd saw
    the FC reboot)."""
    mapped, after_reboot, t0 = 0, 0, time.monotonic()
    while time.monotonic() - t0 < WALL_CAP_S and sim.time < until_sim_s and not sim.route_finished(0):
        frame = cam.slot.take(timeout=0.5)
        if frame is None:
            continue
        a = assoc.associate(frame)
        if a is None:
            if reanchor is not None and assoc.last_skip == "frame_paused":
                reanchor.offer(frame)
            continue
        mapper.integrate(a.depth, a.intrinsics, a.camera_pose, a.stamp)
        mapped += 1
        after_reboot += link.fc_epoch() > 0
    return mapped, after_reboot


@pytest.mark.slow
@pytest.mark.parametrize("case", ["moved", "kept", "moved_no_reanchor"])
def test_fc_reboot_in_flight_keeps_the_map_frame(case, tmp_path, udp_port):
    load_kernels()
    world = build_world("small_house", 0)
    sim = Simulation(world, 1, seed=1, speed=SPEED, noise=WHITE, mavlink_base_port=udp_port,
                     camera_dir=str(tmp_path), route="builtin")
    link = VehicleLink(LinkConfig(connection=f"udpin:127.0.0.1:{udp_port}"))
    cam = SocketDepthSource(SocketSourceConfig(sim.vehicle(0).camera_path), fc=link)
    mapper = Mapper(MapperConfig())
    assoc = FrameAssociator(link)
    reanchor = None if case == "moved_no_reanchor" else FrameReanchor(link.frames, mapper, CameraMount())
    gt, gt_origin = world.ground_truth(0.1)
    link.start()
    cam.start()
    sim.start()
    try:
        assert wait_until(lambda: not link.odometry_stale(), 5.0)
        before, _ = fly_and_map(link, cam, assoc, mapper, reanchor, sim, REBOOT_AT_S)
        t_reboot_sim = sim.time
        truth_old = map_to_world(sim.vehicle(0).odometry, t_reboot_sim, link.odometry.origin_enu)
        acc_before = map_accuracy(mapper.grid.copy(), lambda p: p @ truth_old[:3, :3].T + truth_old[:3, 3],
                                  gt, gt_origin)
        version_before = mapper.version
        sim.reboot_fc(0, downtime_s=2.0, move_origin=case != "kept", turn_rad=0.3)
        t_reboot = time.monotonic()
        resumed_at = []
        frames = link.frames
        original_reanchor = frames.reanchor

        def timed_reanchor(*args):
            ok = original_reanchor(*args)
            if ok:
                resumed_at.append(time.monotonic())
            return ok

        frames.reanchor = timed_reanchor
        after, in_new_frame = fly_and_map(link, cam, assoc, mapper, reanchor, sim, REBOOT_AT_S + AFTER_S)
    finally:
        sim.stop()
        cam.stop()
        link.stop()
    odo = sim.vehicle(0).odometry
    acc_after = map_accuracy(mapper.grid, lambda p: p @ truth_old[:3, :3].T + truth_old[:3, 3], gt, gt_origin)
    # Truth of the correction: the new frame's raw map coordinates into the old map frame.
    shift = np.eye(4)
    shift[:3, 3] = link.odometry.origin_enu
    true_correction = np.linalg.inv(shift) @ sim.fc_frame_transform(0, t_reboot_sim - 0.1, sim.time) @ shift
    err_m, err_deg = offset_error(frames.correction, true_correction)
    report = {
        "case": case,
        "frames_mapped_before": before,
        "frames_mapped_after": after,
        "frames_mapped_in_new_frame": in_new_frame,
        "fc_reboots": link.counters["fc_reboots"],
        "frame": {k: v for k, v in frames.status().items() if k != "correction"},
        "reanchor": None if reanchor is None else reanchor.status(),
        "reboot_to_resumed_s": round(resumed_at[0] - t_reboot, 2) if resumed_at else None,
        "true_frame_move_m": round(float(np.linalg.norm(true_correction[:3, 3])), 2),
        "correction_error_m": round(err_m, 3),
        "correction_error_xyz_m": [round(float(v), 3) for v in (frames.correction - true_correction)[:3, 3]],
        "hold_guess_error_m": None if reanchor is None or reanchor.last_result is None else round(float(
            np.linalg.norm(np.array(reanchor.last_result["guess_shift_m"]) - true_correction[:3, 3])), 3),
        "correction_error_deg": round(err_deg, 2),
        "precision_before": round(acc_before["precision"], 4),
        "precision_after": round(acc_after["precision"], 4),
        "precision_tol1_before": round(acc_before["precision_tol1"], 4),
        "precision_tol1_after": round(acc_after["precision_tol1"], 4),
        "sim_lag_resets": sim.lag_resets,
        "origin_moves": len(odo.frame_log) - 1,
    }
    print(json.dumps(report))
    assert report["fc_reboots"] == 1, report
    assert before >= 30, report
    counters = report["frame"]["counters"]
    if case == "kept":
        assert counters.get("breaks_continuous") == 1 and not counters.get("breaks_paused"), report
        assert err_m < 0.3 and err_deg < 1.0, report
        assert in_new_frame >= 20, report
    elif case == "moved":
        assert report["true_frame_move_m"] > 2.0
        assert counters.get("breaks_paused") == 1, report
        if counters.get("anchors"):
            # Re-anchored: the correction matches the truth and mapping went on in the map frame.
            assert err_m < 0.15 and err_deg < 1.5, report
            assert frames.paused is None and in_new_frame > 0, report
        else:
            # The new views did not pin the frame down before the route ended (a camera looking along
            # a room sees nothing that fixes the position along it): still paused, with the reason.
            assert "re-anchoring:" in frames.paused and in_new_frame == 0, report
            assert reanchor.status()["counters"]["refused"] >= 1, report
    else:
        assert counters.get("breaks_paused") == 1 and frames.paused is not None, report
        # Only frames of the old frame, already on their way when the FC went silent.
        assert in_new_frame == 0 and after <= 5, report
        assert mapper.version <= version_before + after
    # No shifted copy: the map's occupied cells still lie on the world's surfaces.
    assert acc_after["precision_tol1"] >= acc_before["precision_tol1"] - 0.02, report
    assert acc_after["precision_tol1"] >= 0.95, report

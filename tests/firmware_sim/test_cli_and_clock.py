"""The coopd-sim command line, and one simulated clock shared by MAVLink and the camera at --speed K."""

from __future__ import annotations

import json
import socket
import subprocess
import sys
import time
from pathlib import Path

from firmware_sim.simulation import Simulation
from firmware_sim.worlds import build_world

from .mavlink_client import Client
from .test_camera import read_frame

ROOT = Path(__file__).resolve().parents[2]


def test_cli_runs_and_reports_endpoints(tmp_path, port_block):
    cmd = [
        sys.executable,
        "-m",
        "firmware_sim.cli",
        "--world",
        "maze",
        "--vehicles",
        "2",
        "--seed",
        "1",
        "--speed",
        "5",
        "--duration",
        "3",
        "--route",
        "builtin",
        "--mavlink-port",
        str(port_block),
        "--gcs-port",
        "0",
        "--camera-dir",
        str(tmp_path),
        "--no-camera",
    ]
    out = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    lines = out.stdout.strip().splitlines()
    first, last = json.loads(lines[0]), json.loads(lines[-1])
    assert [v["system_id"] for v in first["vehicles"]] == [1, 2]
    assert first["vehicles"][1]["mavlink_target"] == f"udp://127.0.0.1:{port_block + 1}"
    assert "mavlink_gcs_target" not in first["vehicles"][1]  # --gcs-port 0: no GCS instance
    assert last["sim_time_s"] >= 3.0


def test_cli_ardupilot_personality_on_both_instances(port_block):
    """coopd-sim --autopilot ardupilot: an ArduCopter on the onboard and the GCS port (AUTO: the route)."""
    gcs_port = port_block + 4
    onboard, gcs = Client(port_block), Client(gcs_port)
    cmd = [sys.executable, "-m", "firmware_sim.cli", "--world", "small_house", "--autopilot", "ardupilot",
           "--route", "builtin", "--speed", "2", "--duration", "4", "--no-camera",
           "--mavlink-port", str(port_block), "--gcs-port", str(gcs_port)]
    proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        first = json.loads(proc.stdout.readline())
        assert first["vehicles"][0]["autopilot"] == "ardupilot"
        assert first["vehicles"][0]["mavlink_gcs_target"] == f"udp://127.0.0.1:{gcs_port}"
        for c in (onboard, gcs):
            hb = c.wait("HEARTBEAT", timeout=15)
            assert hb is not None and hb.autopilot == 3 and hb.custom_mode == 3  # ARDUPILOTMEGA, AUTO
        assert proc.wait(timeout=60) == 0
    finally:
        proc.kill()
        proc.wait()
        onboard.conn.close()
        gcs.conn.close()


def test_cli_rejects_bad_options():
    cmd = [
        sys.executable,
        "-m",
        "firmware_sim.cli",
        "--world",
        "maze",
        "--camera-res",
        "0x5",
        "--duration",
        "1",
    ]
    out = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert out.returncode == 2 and "coopd-sim:" in out.stderr


def test_speed_runs_one_clock_for_mavlink_and_camera(tmp_path, port_block):
    world = build_world("small_house", seed=0)
    sim = Simulation(world, 1, seed=0, speed=5.0, mavlink_base_port=port_block, camera_dir=str(tmp_path))
    sim.start()
    client = Client(port_block, 1)
    cam = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    try:
        assert client.wait("HEARTBEAT") is not None
        cam.connect(sim.vehicle(0).camera_path)
        w0, s0 = time.monotonic(), sim.time
        time.sleep(1.0)
        wall, sim_dt = time.monotonic() - w0, sim.time - s0
        # Paced to at most K x wall time (on a loaded machine it may fall behind, never run ahead).
        assert 0.2 < sim_dt / wall < 5.5
        # Keep up with the camera for a while, then compare its newest capture time with the clock.
        deadline = time.monotonic() + 0.5
        while time.monotonic() < deadline:
            h, _ = read_frame(cam)
        now_us = sim.time * 1e6
        assert 0 <= now_us - h["t_us"] < 400_000
        assert h["t_us"] % 4000 == 0  # captured on a physics step of the simulated clock
        client.drain()  # drop what queued up (a full socket buffer keeps the oldest datagrams)
        fresh = client.wait("ATTITUDE")
        assert fresh is not None and abs(sim.time * 1000 - fresh.time_boot_ms) < 400
    finally:
        cam.close()
        client.conn.close()
        sim.stop()


def test_cli_start_poses(port_block):
    cmd = [
        sys.executable,
        "-m",
        "firmware_sim.cli",
        "--world",
        "small_house",
        "--vehicles",
        "2",
        "--start-poses",
        "3,2.5,90;9,7.5,-45",
        "--duration",
        "0.5",
        "--speed",
        "5",
        "--no-camera",
        "--mavlink-port",
        str(port_block),
        "--gcs-port",
        "0",
    ]
    out = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    vehicles = json.loads(out.stdout.splitlines()[0])["vehicles"]
    assert vehicles[1]["start_pose"][:2] == [9.0, 7.5]
    assert abs(vehicles[1]["start_pose"][3] + 0.7854) < 1e-3
    bad = subprocess.run(
        cmd[:6] + ["--start-poses", "1,2"], cwd=ROOT, capture_output=True, text=True, timeout=60
    )
    assert bad.returncode == 2

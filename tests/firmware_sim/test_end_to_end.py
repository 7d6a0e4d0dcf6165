"""What coopd will do: three vehicles on their routes, each read over MAVLink and its camera socket."""

from __future__ import annotations

import math
import socket
import time

import numpy as np
import pytest

from firmware_sim.simulation import Simulation
from firmware_sim.worlds import build_world

from .mavlink_client import Client
from .test_camera import read_frame


@pytest.mark.slow
def test_three_vehicles_stream_odometry_and_depth(tmp_path, port_block):
    world = build_world("small_house", seed=1)
    sim = Simulation(
        world, 3, seed=1, speed=2.0, route="builtin", mavlink_base_port=port_block, camera_dir=str(tmp_path)
    )
    clients = [Client(port_block + i, i + 1) for i in range(3)]
    cams = []
    sim.start()
    try:
        for c in clients:
            assert c.wait("HEARTBEAT") is not None
        for v in sim.vehicles:
            s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
            s.connect(v.camera_path)
            cams.append(s)
        frames = {i: [] for i in range(3)}
        odometry = {i: [] for i in range(3)}
        deadline = time.monotonic() + 5.0
        while time.monotonic() < deadline:
            for i, s in enumerate(cams):
                s.setblocking(False)
                try:
                    s.recv(1, socket.MSG_PEEK)
                except BlockingIOError:
                    continue
                s.setblocking(True)
                frames[i].append(read_frame(s))
            for i, c in enumerate(clients):
                odometry[i] += [m for m in c.drain() if m.get_type() == "ODOMETRY"]
            time.sleep(0.01)
        for i in range(3):
            seqs = [h["seq"] for h, _ in frames[i]]
            assert len(seqs) >= 15, (i, len(seqs))
            assert seqs == list(range(seqs[0], seqs[0] + len(seqs)))  # a reader that keeps up loses nothing
            img = np.frombuffer(frames[i][-1][1], "<u2")
            assert (img > 0).mean() > 0.3
            first, last = odometry[i][0], odometry[i][-1]
            assert math.hypot(first.x, first.y) < 0.5  # each reports in its own start frame
            assert last.z < -0.5  # and is flying its route
            assert last.time_usec > first.time_usec
        # Same clock: the newest frame and the newest odometry are close in simulated time.
        for i in range(3):
            assert abs(frames[i][-1][0]["t_us"] - odometry[i][-1].time_usec) < 1_000_000
    finally:
        for s in cams:
            s.close()
        for c in clients:
            c.conn.close()
        sim.stop()

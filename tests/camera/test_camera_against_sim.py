"""The camera socket client against firmware_sim's camera publisher: exact frames, timing, restart."""

import time

import numpy as np
import pytest

from coopd.camera import SocketDepthSource, SocketSourceConfig
from firmware_sim.camera import CameraConfig
from firmware_sim.simulation import Simulation
from firmware_sim.worlds import build_world


@pytest.fixture(scope="module")
def world():
    return build_world("small_house", 0)


def test_frames_arrive_exactly_and_survive_a_driver_restart(world, tmp_path):
    sent = {}
    sim = Simulation(world, 1, seed=0, speed=4.0, mavlink=False, camera_dir=str(tmp_path))
    sim.frame_sink = lambda i, hdr, z16: sent.__setitem__(hdr["seq"], z16.copy()) if len(sent) < 200 else None
    src = SocketDepthSource(SocketSourceConfig(sim.vehicle(0).camera_path, backoff_s=(0.05, 0.5)))
    src.start()
    sim.start()
    try:
        frames = []
        deadline = time.monotonic() + 10
        while len(frames) < 12 and time.monotonic() < deadline:
            f = src.slot.take(timeout=1.0)
            if f is not None:
                frames.append(f)
        assert len(frames) == 12, src.status()
        cfg = CameraConfig()
        fx, fy, cx, cy = cfg.intrinsics()
        for f in frames:
            assert f.depth.shape == (cfg.height, cfg.width) and f.intrinsics.fx == pytest.approx(fx)
            assert np.array_equal(f.depth, sent[f.seq])  # byte-exact through the socket
            assert abs(f.t_fc - f.seq / cfg.rate_hz) < 0.005  # FC time base, camera at 10 Hz
        assert (frames[-1].depth > 0).mean() > 0.5  # the house is in view
        sim.stop()
        assert _wait(lambda: not src.connected, 3.0)
        sim2 = Simulation(world, 1, seed=0, speed=4.0, mavlink=False, camera_dir=str(tmp_path))
        sim2.start()
        try:
            src.slot.take()  # discard a frame left from the first driver
            f = src.slot.take(timeout=5.0)
            assert f is not None and src.counters["connects"] >= 2
        finally:
            sim2.stop()
    finally:
        src.stop()
        sim.stop()


def _wait(pred, timeout):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline and not pred():
        time.sleep(0.02)
    return pred()

"""Hostile input on every port: random bytes, malformed MAVLink, absurd fields, vanishing clients."""

from __future__ import annotations

import math
import socket
import struct
import time

import numpy as np
import pytest
from pymavlink.dialects.v20 import common as mav

from firmware_sim.simulation import Simulation
from firmware_sim.worlds import build_world

from .mavlink_client import Client

NASTY = [math.nan, math.inf, -math.inf, 1e38, -1e38, 0.0, -1.0, 2**31, 65535.0]


@pytest.fixture
def running(port_block, tmp_path):
    world = build_world("small_house", seed=0)
    sim = Simulation(world, 1, seed=0, speed=4.0, mavlink_base_port=port_block, camera_dir=str(tmp_path))
    sim.start()
    client = Client(port_block, 1)
    assert client.wait("HEARTBEAT") is not None
    yield sim, client
    sim.stop()
    client.conn.close()


class Paced:
    """Wraps a pymavlink MAVLink object; sleeps briefly every few sends so UDP buffers never overflow."""

    def __init__(self, mav_obj):
        self._mav, self._n = mav_obj, 0

    def __getattr__(self, name):
        fn = getattr(self._mav, name)

        def paced(*args):
            self._n += 1
            if self._n % 40 == 0:
                time.sleep(0.02)
            return fn(*args)

        return paced


def send_raw(sim, payloads) -> None:
    """Send datagrams straight at the vehicle's bound port, paced so the loop stays bounded."""
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    addr = ("127.0.0.1", sim.vehicle(0).link.bound_port)
    for k, p in enumerate(payloads):
        s.sendto(p, addr)
        if k % 50 == 49:
            time.sleep(0.01)
    s.close()


def assert_alive(sim, client) -> None:
    """The sim thread runs, time advances, telemetry flows and commands are still answered."""
    t0 = sim.time
    time.sleep(0.3)
    assert sim.failure is None
    assert sim._thread is not None and sim._thread.is_alive()
    assert sim.time > t0 + 0.1
    assert client.wait("HEARTBEAT", timeout=3) is not None
    assert client.command(mav.MAV_CMD_REQUEST_MESSAGE, mav.MAVLINK_MSG_ID_HOME_POSITION) == 0


def test_random_bytes_and_broken_frames(running):
    sim, client = running
    rng = np.random.default_rng(1234)
    junk = [rng.integers(0, 256, int(rng.integers(0, 1500)), dtype=np.uint8).tobytes() for _ in range(300)]
    v2 = [
        bytes([0xFD, int(rng.integers(0, 256))]) + rng.integers(0, 256, 300, dtype=np.uint8).tobytes()
        for _ in range(100)
    ]
    v1 = [bytes([0xFE, 9]) + rng.integers(0, 256, 14, dtype=np.uint8).tobytes() for _ in range(100)]
    good = client.mav.heartbeat_encode(6, 8, 0, 0, 0, 3).pack(client.mav)
    truncated = [good[:k] for k in range(len(good))]
    bad_crc = [good[:-2] + b"\x00\x00"] * 20
    unknown_id = [bytearray(good) for _ in range(20)]
    for b in unknown_id:
        b[7:10] = struct.pack("<I", 0xFFFF00)[:3]
    send_raw(sim, junk + v2 + v1 + truncated + bad_crc + [bytes(b) for b in unknown_id] + [b"\xfd" * 65000])
    time.sleep(0.5)
    stats = sim.vehicle(0).link.stats
    assert stats["rx_bad_data"] + stats["rx_parse_errors"] > 50
    assert_alive(sim, client)


def test_absurd_field_values(running):
    sim, client = running
    m = Paced(client.mav)
    for cmd in list(range(0, 600, 7)) + [
        16,
        20,
        21,
        22,
        115,
        176,
        178,
        179,
        192,
        300,
        400,
        510,
        511,
        512,
        520,
    ]:
        for v in NASTY[:4]:
            m.command_long_send(1, 1, cmd, 0, v, v, v, v, v, v, v)
            m.command_int_send(1, 1, 6, cmd, 0, 0, v, v, v, v, 2**31 - 1, -(2**31), v)
    for frame in range(0, 26):
        for v in NASTY:
            m.set_position_target_local_ned_send(0, 1, 1, frame, 0, v, v, v, v, v, v, v, v, v, v, v)
    m.param_set_send(1, 1, b"\xff\xfe\x00junk", math.nan, 9)
    m.param_set_send(1, 1, b"MIS_TAKEOFF_ALT", math.nan, mav.MAV_PARAM_TYPE_REAL32)
    m.param_request_read_send(1, 1, b"", 30000)
    m.mission_item_int_send(1, 1, 5, 0, 16, 0, 1, 0, 0, 0, 0, 0, 0, 0, 0)
    m.mission_count_send(1, 1, 65535, 0)
    m.mission_count_send(1, 1, 3, 7)
    m.mission_request_int_send(1, 1, 60000, 0)
    m.mission_set_current_send(1, 1, 9999)
    m.mission_clear_all_send(1, 1, 99)
    time.sleep(0.5)
    assert sim.vehicle(0).link.stats["rx_messages"] > 900
    assert sim.vehicle(0).fc.params["MIS_TAKEOFF_ALT"] == 2.5  # NaN refused
    assert_alive(sim, client)
    # Still flyable after all that.
    assert client.command(mav.MAV_CMD_COMPONENT_ARM_DISARM, 1) == 0
    assert client.command(mav.MAV_CMD_NAV_TAKEOFF, *[math.nan] * 7) == 0
    assert client.wait("LOCAL_POSITION_NED", lambda x: x.z < -2.0, timeout=10) is not None


def test_messages_for_other_systems_are_ignored(running):
    sim, client = running
    client.mav.command_long_send(42, 1, mav.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0)
    time.sleep(0.5)
    assert not sim.vehicle(0).fc.armed
    assert sim.vehicle(0).link.stats["rx_foreign"] >= 1


def test_abandoned_mission_upload_times_out(running):
    sim, client = running
    client.mav.mission_count_send(1, 1, 5, 0)
    assert client.wait("MISSION_REQUEST_INT", lambda m: m.seq == 0) is not None
    ack = client.wait("MISSION_ACK", timeout=10)
    assert ack is not None and ack.type == mav.MAV_MISSION_OPERATION_CANCELLED
    assert sim.vehicle(0).link.stats["mission_upload_timeouts"] == 1
    assert sim.vehicle(0).fc.mission == []
    assert_alive(sim, client)


def test_vanishing_clients(running, port_block):
    sim, client = running
    client.conn.close()  # the GCS disappears: the vehicle keeps sending into the void
    cam = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    cam.connect(sim.vehicle(0).camera_path)
    cam.recv(1000)  # mid-frame
    cam.close()
    for _ in range(5):  # half-open TCP-like churn on the Unix socket
        s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        s.connect(sim.vehicle(0).camera_path)
        s.send(b"hello?" * 100)
        s.close()
    time.sleep(1.0)
    assert sim.vehicle(0).publisher.clients == {}
    again = Client(port_block, 1)
    try:
        assert_alive(sim, again)
    finally:
        again.conn.close()

"""The link's receive path without a network: datagram boundaries, foreign systems, TCP and serial."""

import os
import socket
import threading
import time

import numpy as np
from pymavlink.dialects.v20 import common as mav
from sim_helpers import wait_until

from coopd.vehicle import LinkConfig, VehicleLink
from coopd.vehicle.link import IDLE_READ_TIMEOUT_S, READ_TIMEOUT_S
from coopd.vehicle.transport import Endpoint, Transport

FC = mav.MAVLink(None, 7, 1)


def heartbeat(enc=FC):
    return enc.heartbeat_encode(mav.MAV_TYPE_QUADROTOR, mav.MAV_AUTOPILOT_PX4, 0, 0, 3, 3).pack(enc)


def odometry(t, x, reset=0):
    m = FC.odometry_encode(
        int(t * 1e6),
        1,
        12,
        x,
        0.0,
        -1.0,
        [1.0, 0, 0, 0],
        0,
        0,
        0,
        0,
        0,
        0,
        [float("nan")] * 21,
        [float("nan")] * 21,
        reset,
        0,
        100,
    )
    return m.pack(FC)


class Recorder(Transport):
    """A datagram transport that records what the link sends."""

    def __init__(self):
        super().__init__(Endpoint("udpin", "127.0.0.1", 1))
        self.sent = []
        self.timeouts = []

    is_open = True

    def read(self, timeout):
        self.timeouts.append(timeout)
        return b""

    def write(self, data):
        self.sent.append(data)

    def open(self):
        pass

    def close(self):
        pass


def test_a_truncated_datagram_does_not_swallow_the_next():
    link = VehicleLink(LinkConfig(connection="udpin:127.0.0.1:1"), transport=Recorder())
    now = time.monotonic()
    link._ingest(heartbeat()[:9], now)
    link._ingest(heartbeat(), now)
    assert link.target_system == 7 and link.counters["rx_partial_discarded"] == 1
    link._ingest(odometry(1.0, 2.0) + odometry(1.02, 2.1), now)  # two packets in one datagram
    assert len(link.poses) == 2 and np.allclose(link.poses.latest().position, [0, 0.1, 0])


def test_the_link_waits_long_on_reads_while_no_fc_is_heard():
    """No FC yet (or lost): the loop waits IDLE_READ_TIMEOUT_S per read instead of polling at
    READ_TIMEOUT_S; once the FC is heard, short reads keep the timers and replies prompt."""
    rec = Recorder()
    link = VehicleLink(LinkConfig(connection="udpin:127.0.0.1:1"), transport=rec)
    link.step(time.monotonic())
    assert link.state != "ok" and rec.timeouts == [IDLE_READ_TIMEOUT_S]
    link._ingest(heartbeat(), time.monotonic())
    link._update_state(time.monotonic())
    link.step(time.monotonic())
    assert link.state == "ok" and rec.timeouts[-1] == READ_TIMEOUT_S < IDLE_READ_TIMEOUT_S


def test_only_the_locked_system_is_followed():
    link = VehicleLink(LinkConfig(connection="udpin:127.0.0.1:1"), transport=Recorder())
    now = time.monotonic()
    link._ingest(heartbeat(), now)
    other = mav.MAVLink(None, 9, 1)
    link._ingest(heartbeat(other), now)
    link._ingest(
        other.odometry_encode(
            10**6, 1, 12, 5.0, 0, 0, [1.0, 0, 0, 0], 0, 0, 0, 0, 0, 0, [0.0] * 21, [0.0] * 21, 0, 0, 100
        ).pack(other),
        now,
    )
    assert link.target_system == 7 and link.counters["rx_foreign"] == 2 and len(link.poses) == 0


def test_tcp_connection_and_reconnect():
    server = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    server.bind(("127.0.0.1", 0))
    server.listen(2)
    port = server.getsockname()[1]
    got = []

    def serve(n_conn):
        for k in range(n_conn):
            conn, _ = server.accept()
            with conn:
                # a stream: packets may be split anywhere
                data = heartbeat() + b"".join(odometry(1.0 + 0.02 * i + 10 * k, 0.01 * i) for i in range(20))
                for i in range(0, len(data), 37):
                    conn.sendall(data[i : i + 37])
                conn.settimeout(1.0)
                try:
                    got.append(conn.recv(4096))
                except OSError:  # timed out, or the link already closed (reset) at the test's end
                    got.append(b"")
                time.sleep(0.2)

    th = threading.Thread(target=serve, args=(2,), daemon=True)
    th.start()
    link = VehicleLink(LinkConfig(connection=f"tcp:127.0.0.1:{port}", reopen_backoff_s=(0.05, 0.2)))
    link.start()
    try:
        assert wait_until(lambda: len(link.poses) >= 20, 3.0), link.status()
        assert wait_until(lambda: link.transport.counters["reopens"] >= 2, 3.0), link.status()
        assert wait_until(lambda: link.poses.latest().t_fc > 10.0, 3.0)
        assert any(got)  # our HEARTBEAT reached the FC side
    finally:
        link.stop()
        th.join(2)
        server.close()


def test_serial_over_a_pseudo_terminal():
    master, slave = os.openpty()
    link = VehicleLink(LinkConfig(connection=f"{os.ttyname(slave)},921600"))
    link.start()
    try:
        assert wait_until(lambda: link.transport.is_open, 2.0)  # pyserial puts the tty in raw mode on open
        data = heartbeat() + b"".join(odometry(2.0 + 0.02 * i, 0.0) for i in range(10))
        os.write(master, data)
        assert wait_until(lambda: len(link.poses) == 10, 3.0), link.status()
        assert link.status()["link"] == "ok"
    finally:
        link.stop()
        os.close(master)
        os.close(slave)

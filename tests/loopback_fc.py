"""A minimal flight controller for link tests: pymavlink on the test's end of a loopback channel
(UDP, TCP or a pty pair), sending HEARTBEATs as a given system id and recording what coopd sends."""

import contextlib
import os
import select
import socket
import time
import tty

from pymavlink.dialects.v20 import common as mav

LOOPBACK = {socket.AF_INET: "127.0.0.1", socket.AF_INET6: "::1"}


def free_port(family=socket.AF_INET, kind=socket.SOCK_DGRAM) -> int:
    """A port the kernel just handed out on loopback (free for UDP and, almost surely, TCP)."""
    with socket.socket(family, kind) as s:
        s.bind((LOOPBACK[family], 0))
        return s.getsockname()[1]


class UdpChannel:
    """UDP socket; bound (coopd sends to us: udpout) or not (we send to coopd: udpin)."""

    def __init__(self, family, bind_port: int | None = None, send_to: tuple | None = None):
        self.sock = socket.socket(family, socket.SOCK_DGRAM)
        if bind_port is not None:
            self.sock.bind((LOOPBACK[family], bind_port))
        self.target = send_to

    def send(self, data: bytes) -> None:
        if self.target is not None:
            with contextlib.suppress(OSError):  # ECONNREFUSED while coopd is not bound yet
                self.sock.sendto(data, self.target)

    def recv(self, timeout: float) -> bytes:
        if not select.select([self.sock], [], [], timeout)[0]:
            return b""
        try:
            data, source = self.sock.recvfrom(65536)
        except OSError:
            return b""
        self.target = self.target or source  # udpout: answer whoever sent to our port
        return data

    def close(self) -> None:
        self.sock.close()


class TcpChannel:
    """TCP: we listen (coopd's tcp: connects) or connect, retrying (coopd's tcpin: listens)."""

    def __init__(self, family, listen_port: int | None = None, connect_to: tuple | None = None):
        self.family, self.connect_to, self.conn = family, connect_to, None
        self.listener = None
        if listen_port is not None:
            self.listener = socket.socket(family, socket.SOCK_STREAM)
            self.listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            self.listener.bind((LOOPBACK[family], listen_port))
            self.listener.listen(1)

    def _ensure(self, timeout: float) -> None:
        if self.conn is not None:
            return
        if self.listener is not None:
            if select.select([self.listener], [], [], timeout)[0]:
                self.conn, _ = self.listener.accept()
            return
        try:  # a blocking connect: a non-blocking one (send's timeout 0) that gives up can still reach
            # the listener's backlog and show the server a second, dead connection
            self.conn = socket.create_connection(self.connect_to, timeout=max(timeout, 1.0))
        except OSError:
            time.sleep(timeout)

    def send(self, data: bytes) -> None:
        self._ensure(0.0)
        if self.conn is not None:
            with contextlib.suppress(OSError):
                self.conn.sendall(data)

    def recv(self, timeout: float) -> bytes:
        self._ensure(timeout)
        if self.conn is None or not select.select([self.conn], [], [], timeout)[0]:
            return b""
        try:
            return self.conn.recv(65536)
        except OSError:
            return b""

    def close(self) -> None:
        for s in (self.conn, self.listener):
            if s is not None:
                s.close()


class PtyChannel:
    """A pty pair: coopd opens the slave's path as a serial port, we speak on the master."""

    def __init__(self):
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)  # no echo, no line discipline before pyserial configures it
        self.path = os.ttyname(self.slave)

    def send(self, data: bytes) -> None:
        with contextlib.suppress(OSError):
            os.write(self.master, data)

    def recv(self, timeout: float) -> bytes:
        if not select.select([self.master], [], [], timeout)[0]:
            return b""
        try:
            return os.read(self.master, 65536)
        except OSError:
            return b""

    def close(self) -> None:
        os.close(self.master)
        os.close(self.slave)


class LoopbackFc:
    """The flight controller's side: HEARTBEAT as `system_id` (autopilot component 1), and every
    message coopd sends, parsed, in `received`."""

    def __init__(self, channel, system_id: int = 1, signing_key: bytes | None = None):
        self.channel = channel
        self.mav = mav.MAVLink(self, srcSystem=system_id, srcComponent=mav.MAV_COMP_ID_AUTOPILOT1)
        self.mav.robust_parsing = True
        if signing_key is not None:
            self.mav.signing.secret_key = signing_key
            self.mav.signing.link_id = 0
            self.mav.signing.timestamp = int((time.time() - 1420070400) * 100_000)
            self.mav.signing.sign_outgoing = True
        self.received: list = []

    def write(self, buf) -> None:  # pymavlink's file-like output
        self.channel.send(bytes(buf))

    def heartbeat(self, system_status=mav.MAV_STATE_ACTIVE) -> None:
        self.mav.send(
            self.mav.heartbeat_encode(mav.MAV_TYPE_QUADROTOR, mav.MAV_AUTOPILOT_PX4, 0, 0, system_status)
        )

    def odometry(self, t_s: float, position_ned=(0.0, 0.0, -1.0)) -> None:
        """ODOMETRY at FC time t_s: hovering at position_ned, level, facing north."""
        nan21 = [float("nan")] * 21
        self.mav.send(self.mav.odometry_encode(
            int(t_s * 1e6), mav.MAV_FRAME_LOCAL_NED, mav.MAV_FRAME_BODY_FRD, *position_ned,
            [1.0, 0.0, 0.0, 0.0], 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, nan21, nan21,
            0, mav.MAV_ESTIMATOR_TYPE_VIO, 100,
        ))

    def pump(self, timeout: float) -> None:
        """Read and parse what arrived within timeout s."""
        data = self.channel.recv(timeout)
        if data:
            for m in self.mav.parse_buffer(data) or []:
                if m.get_type() != "BAD_DATA":
                    self.received.append(m)

    def messages(self, kind: str) -> list:
        return [m for m in self.received if m.get_type() == kind]

    def run_until(self, done, seconds: float = 5.0, period: float = 0.1, send=None) -> bool:
        """Heartbeat (and `send()`) every `period` s until done() or `seconds` pass; done()'s last value."""
        deadline = time.monotonic() + seconds
        next_send = 0.0
        while time.monotonic() < deadline:
            if done():
                return True
            if time.monotonic() >= next_send:
                next_send = time.monotonic() + period
                self.heartbeat()
                if send is not None:
                    send(self)
            self.pump(0.02)
        return bool(done())

    def close(self) -> None:
        self.channel.close()

"""Byte transports behind MAVLink connection strings: udpin/udpout/tcp/serial, all non-blocking."""

from __future__ import annotations

import abc
import contextlib
import logging
import select
import socket
from dataclasses import dataclass

log = logging.getLogger("coopd.vehicle")

MAX_READ = 65536


@dataclass(frozen=True)
class Endpoint:
    """A parsed connection string."""

    kind: str  # "udpin", "udpout", "tcp", "serial"
    host: str = ""
    port: int = 0
    device: str = ""
    baud: int = 0


def parse_connection(text: str) -> Endpoint:
    """Parse `udpin:0.0.0.0:14540`, `udp:…` (= udpin), `udpout:host:port`, `tcp:host:port`,
    `/dev/ttyACM0,921600` or `serial:/dev/ttyACM0:921600`; raises ValueError with the reason."""
    if not isinstance(text, str) or not text or len(text) > 256:
        raise ValueError("connection string must be a non-empty string of at most 256 characters")
    kind, _, rest = text.partition(":")
    if kind in ("udp", "udpin", "udpout", "tcp"):
        host, _, port = rest.rpartition(":")
        if not host or not port.isdigit() or not 0 < int(port) < 65536:
            raise ValueError(f"{text!r}: expected {kind}:host:port with a port in 1..65535")
        return Endpoint("udpin" if kind == "udp" else kind, host, int(port))
    if kind == "serial":
        device, _, baud = rest.rpartition(":")
    elif text.startswith("/") or text.upper().startswith("COM"):
        device, _, baud = text.partition(",")
    else:
        raise ValueError(f"{text!r}: unknown connection type (udpin:, udpout:, tcp:, serial:, /dev/…,baud)")
    if not device or not baud.isdigit() or not 50 <= int(baud) <= 20_000_000:
        raise ValueError(f"{text!r}: serial needs a device and a baud rate, e.g. /dev/ttyACM0,921600")
    return Endpoint("serial", device=device, baud=int(baud))


class Transport(abc.ABC):
    """Non-blocking byte pipe; `read` waits at most `timeout` s, `write` never blocks."""

    def __init__(self, endpoint: Endpoint):
        self.endpoint = endpoint
        self.datagrams = endpoint.kind in ("udpin", "udpout")  # each read holds whole MAVLink packets
        self.counters = {"tx_dropped": 0, "rx_errors": 0, "reopens": 0, "peer_changes": 0}

    @property
    @abc.abstractmethod
    def is_open(self) -> bool:
        """True while the underlying socket or port is open."""

    @abc.abstractmethod
    def open(self) -> None:
        """Open (or reopen) the socket or port; failures are raised as OSError."""

    @abc.abstractmethod
    def read(self, timeout: float) -> bytes:
        """Bytes received within timeout s (b"" when none)."""

    peer = None

    def accept_source(self) -> None:  # noqa: B027 - a hook most transports leave empty
        """The last read held valid traffic from the FC (only datagram servers care)."""

    @abc.abstractmethod
    def write(self, data: bytes) -> None:
        """Send without blocking; what cannot be sent now is dropped and counted."""

    @abc.abstractmethod
    def close(self) -> None:
        """Close; a later open() starts over."""


class SocketTransport(Transport):
    """UDP (server or client) and TCP (client) over one socket."""

    def __init__(self, endpoint: Endpoint, connect_timeout: float = 0.5):
        super().__init__(endpoint)
        self.sock: socket.socket | None = None
        self.peer: tuple | None = None
        self.last_source: tuple | None = None
        self.connect_timeout = connect_timeout

    @property
    def is_open(self) -> bool:
        return self.sock is not None

    def open(self) -> None:
        """Bind or connect; raises OSError if that is impossible right now."""
        e = self.endpoint
        if e.kind == "tcp":
            s = socket.create_connection((e.host, e.port), timeout=self.connect_timeout)
            s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            self.peer = (e.host, e.port)
        else:
            s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            if e.kind == "udpin":
                s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
                s.bind((e.host, e.port))
                self.peer = None  # learnt from the first datagram, as MAVLink routers do
            else:
                self.peer = (socket.gethostbyname(e.host), e.port)
        s.setblocking(False)
        self.sock = s

    def read(self, timeout: float) -> bytes:
        s = self.sock
        if s is None:
            return b""
        try:
            ready, _, _ = select.select([s], [], [], timeout)
        except (OSError, ValueError):
            self.counters["rx_errors"] += 1
            return b""
        if not ready:
            return b""
        try:
            if self.endpoint.kind == "tcp":
                data = s.recv(MAX_READ)
                if not data:
                    log.warning("MAVLink TCP peer %s:%d closed the connection", *self.peer)
                    self.close()
                return data
            data, self.last_source = s.recvfrom(MAX_READ)
            return data
        except (BlockingIOError, InterruptedError):
            return b""
        except OSError:  # ECONNREFUSED on udpout when nobody listens, resets on tcp
            self.counters["rx_errors"] += 1
            if self.endpoint.kind == "tcp":
                self.close()
            return b""

    def accept_source(self) -> None:
        """udpin: reply to whoever sent the last datagram. The link calls this for the first valid FC
        message and then only for the FC's heartbeats, so a stranger's bytes cannot divert our replies
        (one that spoofs the FC's heartbeat can, until the FC's next one: MAVLink without signing)."""
        if self.endpoint.kind == "udpin" and self.last_source is not None and self.last_source != self.peer:
            if self.peer is not None:
                self.counters["peer_changes"] += 1
                if self.counters["peer_changes"] <= 5:
                    log.warning("MAVLink peer moved from %s:%d to %s:%d", *self.peer, *self.last_source)
            self.peer = self.last_source

    def write(self, data: bytes) -> None:
        s, peer = self.sock, self.peer
        if s is None or peer is None:
            self.counters["tx_dropped"] += 1
            return
        try:
            if self.endpoint.kind == "tcp":
                sent = s.send(data)
                if sent < len(data):
                    self.counters["tx_dropped"] += 1  # a partial MAVLink frame is re-synced by the parser
            else:
                s.sendto(data, peer)
        except (BlockingIOError, InterruptedError):
            self.counters["tx_dropped"] += 1
        except OSError:
            self.counters["tx_dropped"] += 1
            if self.endpoint.kind == "tcp":
                self.close()

    def close(self) -> None:
        if self.sock is not None:
            with contextlib.suppress(OSError):
                self.sock.close()
        self.sock = None


class SerialTransport(Transport):
    """A serial port through pyserial, reopened after errors (USB unplug, FC reboot)."""

    def __init__(self, endpoint: Endpoint):
        super().__init__(endpoint)
        self.port = None

    @property
    def is_open(self) -> bool:
        return self.port is not None

    def open(self) -> None:
        import serial  # pyserial; imported here so UDP-only installs never need it

        try:
            self.port = serial.Serial(self.endpoint.device, self.endpoint.baud, timeout=0, write_timeout=0)
        except serial.SerialException as e:
            raise OSError(str(e)) from e

    def read(self, timeout: float) -> bytes:
        p = self.port
        if p is None:
            return b""
        try:
            ready, _, _ = select.select([p.fileno()], [], [], timeout)
            return p.read(min(max(p.in_waiting, 1), MAX_READ)) if ready else b""
        except Exception:  # pyserial raises SerialException/OSError/TypeError when the device vanishes
            self.counters["rx_errors"] += 1
            self.close()
            return b""

    def write(self, data: bytes) -> None:
        p = self.port
        if p is None:
            self.counters["tx_dropped"] += 1
            return
        try:
            p.write(data)
        except Exception:  # write timeout 0 raises SerialTimeoutException when the buffer is full
            self.counters["tx_dropped"] += 1

    def close(self) -> None:
        if self.port is not None:
            with contextlib.suppress(Exception):
                self.port.close()
        self.port = None


def make_transport(connection: str) -> Transport:
    """The transport for a connection string (not yet opened)."""
    e = parse_connection(connection)
    return SerialTransport(e) if e.kind == "serial" else SocketTransport(e)

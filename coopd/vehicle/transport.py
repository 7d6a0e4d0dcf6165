"""Byte transports behind MAVLink connection strings (coopd.vehicle.connection): udpin, udpout, tcp,
tcpin and serial, all non-blocking."""

from __future__ import annotations

import abc
import contextlib
import logging
import select
import socket

from coopd.net import host_port, listening_socket, resolve

from .connection import Endpoint, parse_connection

log = logging.getLogger("coopd.vehicle")

MAX_READ = 65536


def _address(sockaddr) -> str:
    """host:port, IPv6 hosts in brackets, for log lines."""
    return host_port(str(sockaddr[0]), sockaddr[1]) if sockaddr else "?"


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
    """UDP (udpin: listen, udpout: send to) and TCP client over one socket, IPv4 or IPv6."""

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
        """Bind or connect; raises OSError if that is impossible right now (name resolution included)."""
        e = self.endpoint
        if e.kind == "tcp":
            s = socket.create_connection((e.host, e.port), timeout=self.connect_timeout)
            s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            self.peer = s.getpeername()
        else:
            family, address = resolve(e.host, e.port, socket.SOCK_DGRAM, passive=e.kind == "udpin")
            if e.kind == "udpout":
                s = socket.socket(family, socket.SOCK_DGRAM)
                self.peer = address
            else:
                s = listening_socket(family, socket.SOCK_DGRAM)
                try:
                    s.bind(address)
                except OSError:
                    s.close()
                    raise
                self.peer = None  # learnt from the first datagram, as MAVLink routers do
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
                    log.warning("MAVLink TCP peer %s closed the connection", _address(self.peer))
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
                    log.warning(
                        "MAVLink peer moved from %s to %s", _address(self.peer), _address(self.last_source)
                    )
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


class TcpServerTransport(Transport):
    """tcpin: listen and serve one connection at a time (the FC, or a MAVLink router, connects to us).
    A newer connection replaces the current one until that one carried the FC's heartbeat
    (accept_source); after that newcomers are refused and counted, so a stranger can neither
    displace the FC nor hold the port by connecting first."""

    BACKLOG = 4

    def __init__(self, endpoint: Endpoint):
        super().__init__(endpoint)
        self.listener: socket.socket | None = None
        self.conn: socket.socket | None = None
        self.peer: tuple | None = None
        self.confirmed = False
        self.counters.update({"connections": 0, "connections_refused": 0, "connections_replaced": 0})

    @property
    def is_open(self) -> bool:
        return self.listener is not None

    def open(self) -> None:
        e = self.endpoint
        family, address = resolve(e.host, e.port, socket.SOCK_STREAM, passive=True)
        s = listening_socket(family, socket.SOCK_STREAM)
        try:
            s.bind(address)
            s.listen(self.BACKLOG)
        except OSError:
            s.close()
            raise
        s.setblocking(False)
        self.listener = s

    def read(self, timeout: float) -> bytes:
        if self.listener is None:
            return b""
        watched = [self.listener] + ([self.conn] if self.conn is not None else [])
        try:
            ready, _, _ = select.select(watched, [], [], timeout)
        except (OSError, ValueError):
            self.counters["rx_errors"] += 1
            return b""
        if self.listener in ready:
            self._accept()
        if self.conn is None or self.conn not in ready:
            return b""
        try:
            data = self.conn.recv(MAX_READ)
        except (BlockingIOError, InterruptedError):
            return b""
        except OSError:
            self.counters["rx_errors"] += 1
            self._drop_connection()
            return b""
        if not data:
            log.warning("MAVLink TCP peer %s closed the connection; listening again", _address(self.peer))
            self._drop_connection()
        return data

    def _accept(self) -> None:
        try:
            conn, address = self.listener.accept()
        except (BlockingIOError, InterruptedError):
            return
        except OSError:
            self.counters["rx_errors"] += 1
            return
        if self.conn is not None and self.confirmed:
            self.counters["connections_refused"] += 1
            if self.counters["connections_refused"] <= 5:
                log.warning("MAVLink TCP connection from %s refused: the FC is connected from %s",
                            _address(address), _address(self.peer))
            conn.close()
            return
        if self.conn is not None:
            self.counters["connections_replaced"] += 1
            self._drop_connection()
        conn.setblocking(False)
        conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self.conn, self.peer, self.confirmed = conn, address, False
        self.counters["connections"] += 1
        log.info("MAVLink TCP connection from %s", _address(address))

    def accept_source(self) -> None:
        self.confirmed = self.conn is not None

    def _drop_connection(self) -> None:
        if self.conn is not None:
            with contextlib.suppress(OSError):
                self.conn.close()
        self.conn, self.peer, self.confirmed = None, None, False

    def write(self, data: bytes) -> None:
        if self.conn is None:
            self.counters["tx_dropped"] += 1
            return
        try:
            if self.conn.send(data) < len(data):
                self.counters["tx_dropped"] += 1  # a partial MAVLink frame is re-synced by the parser
        except (BlockingIOError, InterruptedError):
            self.counters["tx_dropped"] += 1
        except OSError:
            self.counters["tx_dropped"] += 1
            self._drop_connection()

    def close(self) -> None:
        self._drop_connection()
        if self.listener is not None:
            with contextlib.suppress(OSError):
                self.listener.close()
        self.listener = None


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
    if e.kind == "serial":
        return SerialTransport(e)
    return TcpServerTransport(e) if e.kind == "tcpin" else SocketTransport(e)

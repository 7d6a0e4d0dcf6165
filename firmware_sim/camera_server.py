"""Camera socket protocol server: fan frames out to any number of clients, newest frame wins."""

from __future__ import annotations

import contextlib
import os
import socket
import struct
import threading

import msgpack

MAX_HEADER = 4096
MAX_CLIENTS = 32


def encode_frame(header: dict, payload: bytes) -> bytes:
    """One wire frame: uint32 LE header length, msgpack header, payload."""
    h = msgpack.packb(header, use_bin_type=True)
    if not 1 <= len(h) <= MAX_HEADER:
        raise ValueError("camera header too large")
    return struct.pack("<I", len(h)) + h + payload


class _Client:
    """One connected reader: the frame being written and at most one newer frame waiting."""

    def __init__(self, sock: socket.socket):
        self.sock = sock
        self.current = memoryview(b"")
        self.pending: bytes | None = None


class CameraPublisher:
    """Non-blocking publisher on a Unix stream socket (and optionally TCP on 127.0.0.1)."""

    def __init__(self, unix_path: str | None, tcp_port: int | None = None):
        self.listeners: list[socket.socket] = []
        self.clients: dict[int, _Client] = {}
        self.unix_path = unix_path
        self.tcp_port = None
        self.frames_published = 0
        self.frames_dropped = 0
        self.clients_rejected = 0
        self.send_errors = 0
        self.lock = threading.Lock()  # the sim thread polls while the render thread publishes
        if unix_path:
            with contextlib.suppress(FileNotFoundError):
                os.unlink(unix_path)
            s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
            s.bind(unix_path)
            self._listen(s)
        if tcp_port is not None:
            s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            s.bind(("127.0.0.1", tcp_port))
            self.tcp_port = s.getsockname()[1]
            self._listen(s)

    def _listen(self, s: socket.socket) -> None:
        """Start listening without blocking."""
        s.listen(8)
        s.setblocking(False)
        self.listeners.append(s)

    def fileno_list(self) -> list[int]:
        """Sockets worth waking up for (listeners and clients), for the sim's select loop."""
        with self.lock:
            return [s.fileno() for s in self.listeners] + list(self.clients)

    def poll(self) -> None:
        """Accept new clients, discard anything clients send, notice hang-ups, push queued bytes."""
        with self.lock:
            self._poll()

    def _poll(self) -> None:
        """poll() without the lock."""
        for s in self.listeners:
            for _ in range(8):
                try:
                    conn, _ = s.accept()
                except (BlockingIOError, InterruptedError):
                    break
                except OSError:
                    break
                if len(self.clients) >= MAX_CLIENTS:
                    self.clients_rejected += 1
                    conn.close()
                    continue
                conn.setblocking(False)
                self.clients[conn.fileno()] = _Client(conn)
        for fd, c in list(self.clients.items()):
            try:
                data = c.sock.recv(4096)
                if data == b"":
                    self._drop(fd)
                    continue
            except (BlockingIOError, InterruptedError):
                pass
            except OSError:
                self._drop(fd)
                continue
            self._flush(fd, c)

    def publish(self, frame: bytes) -> None:
        """Queue a frame for every client; a client still busy with an older queued frame loses it."""
        with self.lock:
            self._publish(frame)

    def _publish(self, frame: bytes) -> None:
        """publish() without the lock."""
        self.frames_published += 1
        for fd, c in list(self.clients.items()):
            if len(c.current) == 0:
                c.current = memoryview(frame)
            else:
                if c.pending is not None:
                    self.frames_dropped += 1
                c.pending = frame
            self._flush(fd, c)

    def _flush(self, fd: int, c: _Client) -> None:
        """Write as much as the socket takes now, never blocking."""
        for _ in range(64):
            if len(c.current) == 0:
                if c.pending is None:
                    return
                c.current, c.pending = memoryview(c.pending), None
            try:
                n = c.sock.send(c.current)
            except (BlockingIOError, InterruptedError):
                return
            except OSError:
                self.send_errors += 1
                self._drop(fd)
                return
            c.current = c.current[n:]

    def _drop(self, fd: int) -> None:
        """Forget a client."""
        c = self.clients.pop(fd, None)
        if c is not None:
            with contextlib.suppress(OSError):
                c.sock.close()

    def close(self) -> None:
        """Close every socket and remove the Unix socket file."""
        with self.lock:
            self._close()

    def _close(self) -> None:
        """close() without the lock."""
        for fd in list(self.clients):
            self._drop(fd)
        for s in self.listeners:
            with contextlib.suppress(OSError):
                s.close()
        self.listeners.clear()
        if self.unix_path:
            with contextlib.suppress(OSError):
                os.unlink(self.unix_path)

"""The control socket: a unix socket in the RuntimeDirectory that coopctl talks to.

Protocol, version 1 (docs/operations.md, "Control protocol"); one request per connection:

    client -> daemon   u32 big-endian length N, then N bytes of UTF-8 JSON:
                       {"v": 1, "cmd": "status", "args": {...}}
    daemon -> client   u32 length M, then M bytes of JSON:
                       {"v": 1, "ok": true, "result": {...}}            or
                       {"v": 1, "ok": true, "result": {...}, "blob_bytes": B} + B raw bytes  or
                       {"v": 1, "ok": false, "code": "...", "error": "one line"}

Requests are bounded (max_request_bytes, refused from the length prefix before anything is read),
must arrive completely within timeout_s of the connect, and at most max_clients connections are
open at once (a new one evicts the oldest still sending its request, or else the oldest reply
still being read after evict_reply_after_s, so a slow or stuck client can't lock coopctl out).
A reply must be read completely by a deadline set when it is ready (timeout_s + its size /
min_reply_rate; progress does not move it), and the bytes of replies not yet sent are bounded by
max_reply_buffer_bytes (a blob reply that does not fit next to the others is refused "busy").
One selector thread does all socket I/O; handlers run in a small worker pool so a slow command
never stalls the socket, and quick_commands (status, ping) on a worker of their own so slow
commands holding every worker never delay them. Nothing a client sends can crash the server:
every failure is a counted error reply or a closed connection.
"""

import errno
import json
import logging
import math
import os
import selectors
import socket
import stat
import struct
import threading
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

log = logging.getLogger("coopd.daemon")

PROTOCOL_VERSION = 1
DEFAULT_CONTROL_SOCKET = "/run/coopd/control.sock"
LISTEN_BACKLOG = 256
MAX_SOCKET_PATH = 90
"""Bytes: sun_path holds 107, and the socket is bound first under PATH.<pid>.tmp."""
LENGTH = struct.Struct(">I")
DEFAULT_MAX_REQUEST = 64 * 1024
DEFAULT_MAX_REPLY = 16 * 1024 * 1024
"""coopctl's bound on a reply's JSON part (blobs have their own bound)."""
DEFAULT_MAX_REPLY_BUFFER = 64 * 1024 * 1024
"""Bytes of replies queued for slow readers, all connections together (one reply may exceed it
when it is the only one: a map the daemon holds anyway)."""
DEFAULT_MIN_REPLY_RATE = 4 * 1024 * 1024
"""Bytes/s a reader must at least take: a reply's deadline is timeout_s + its size / this rate."""
EVICT_REPLY_AFTER_S = 0.3
"""A reply still unread after this may be cut when every slot is taken and a client waits."""


class CommandFailed(Exception):
    """Raised by a handler for an operator-facing failure (unknown peer, no global map yet, ...)."""


@dataclass(frozen=True)
class BlobReply:
    """A handler's reply with raw bytes streamed after the JSON (e.g. a map message for dump-map)."""

    result: dict
    data: bytes


Handler = Callable[[dict], "dict | BlobReply"]


def encode_frame(obj: dict) -> bytes:
    body = json.dumps(obj, separators=(",", ":"), allow_nan=False).encode()
    return LENGTH.pack(len(body)) + body


def error_reply(code: str, message: str) -> bytes:
    return encode_frame({"v": PROTOCOL_VERSION, "ok": False, "code": code, "error": message})


# ------------------------------------------------------------------------------------------ server
class _Conn:
    __slots__ = ("sock", "opened", "deadline", "buf", "need", "out", "phase", "peer_uid", "charged",
                 "replied")

    def __init__(self, sock: socket.socket, timeout_s: float):
        self.sock = sock
        self.opened = time.monotonic()
        self.deadline = self.opened + timeout_s
        self.buf = bytearray()
        self.need: int | None = None
        """Body length once the prefix is in."""
        self.out: list[memoryview] = []
        """Reply parts still to send (head, blob): a blob is sent from the handler's bytes, not copied."""
        self.phase = "read"
        self.peer_uid = -1
        self.charged = 0
        """Reply bytes charged to the server's reply buffer for this connection."""
        self.replied = 0.0


class ControlServer:
    """Serves `handlers` (command name -> function(args) -> dict | BlobReply) on a unix socket."""

    COUNTERS = (
        "accepted",
        "served",
        "errors",
        "bad_requests",
        "oversize",
        "timeouts",
        "evicted",
        "handler_errors",
        "unknown_commands",
        "reply_timeouts",
        "evicted_replies",
        "refused_busy",
    )

    def __init__(
        self,
        path,
        handlers: dict[str, Handler],
        *,
        max_request_bytes: int = DEFAULT_MAX_REQUEST,
        max_clients: int = 8,
        timeout_s: float = 5.0,
        mode: int = 0o660,
        group: int | None = None,
        workers: int = 2,
        max_reply_buffer_bytes: int = DEFAULT_MAX_REPLY_BUFFER,
        min_reply_rate: float = DEFAULT_MIN_REPLY_RATE,
        quick_commands=("status",),
    ):
        if max_clients < 1 or max_request_bytes < 64 or timeout_s <= 0:
            raise ValueError("max_clients >= 1, max_request_bytes >= 64 and timeout_s > 0 required")
        if max_reply_buffer_bytes < 1 << 20 or min_reply_rate < 1 << 10:
            raise ValueError("max_reply_buffer_bytes >= 1 MiB and min_reply_rate >= 1 KiB/s required")
        self.path = os.fspath(path)
        if len(os.fsencode(self.path)) > MAX_SOCKET_PATH:
            raise ValueError(f"control socket path {self.path!r} is longer than {MAX_SOCKET_PATH} bytes")
        self.handlers = dict(handlers)
        self.handlers.setdefault("ping", self._ping)
        self.max_request_bytes = max_request_bytes
        self.max_clients = max_clients
        self.timeout_s = timeout_s
        self.mode = mode
        self.group = group
        self.max_reply_buffer_bytes = max_reply_buffer_bytes
        self.min_reply_rate = float(min_reply_rate)
        self.counters = dict.fromkeys(self.COUNTERS, 0)
        self.evict_after_s = min(0.02, timeout_s / 2)
        """A connection that has not sent its whole request after this may be evicted when full."""
        self.evict_reply_after_s = min(EVICT_REPLY_AFTER_S, timeout_s)
        self._buffered = 0
        """Reply bytes charged and not yet sent or dropped (under _done_lock)."""
        self._accepting = False
        self._workers = workers
        self._pool: ThreadPoolExecutor | None = None
        self.quick_commands = frozenset(quick_commands) | {"ping"}
        """Commands answered on a worker of their own: slow ones (merge-now, a big dump-map) holding
        every other worker never keep `status` waiting."""
        self._quick_pool: ThreadPoolExecutor | None = None
        self._sel: selectors.BaseSelector | None = None
        self._listener: socket.socket | None = None
        self._conns: dict[int, _Conn] = {}
        self._done: list[tuple[_Conn, bytes]] = []
        self._done_lock = threading.Lock()
        self._wake_r, self._wake_w = socket.socketpair()
        self._wake_r.setblocking(False)
        self._wake_w.setblocking(False)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.on_thread_start: Callable[[], None] | None = None
        """Called in the server thread when it starts (the daemon applies the thread priority)."""

    # ---------------------------------------------------------------------------- lifecycle
    def start(self) -> "ControlServer":
        self._listener = self._bind()
        self._pool = ThreadPoolExecutor(self._workers, "coopd-control-cmd")
        self._quick_pool = ThreadPoolExecutor(1, "coopd-control-quick")
        self._sel = selectors.DefaultSelector()
        self._sel.register(self._listener, selectors.EVENT_READ, "listen")
        self._accepting = True
        self._sel.register(self._wake_r, selectors.EVENT_READ, "wake")
        self._thread = threading.Thread(target=self._run, name="coopd-control", daemon=True)
        self._thread.start()
        log.info(
            "control socket listening on %s (mode %04o, max %d clients, %d-byte requests, %.1f s timeout)",
            self.path,
            self.mode,
            self.max_clients,
            self.max_request_bytes,
            self.timeout_s,
        )
        return self

    def stop(self) -> None:
        self._stop.set()
        self._wake()
        if self._thread is not None:
            self._thread.join(timeout=5)
        for pool in (self._pool, self._quick_pool):
            if pool is not None:
                pool.shutdown(wait=False, cancel_futures=True)
        for conn in list(self._conns.values()):
            self._close(conn)
        if self._listener is not None:
            self._listener.close()
            try:
                os.unlink(self.path)
            except FileNotFoundError:
                pass
        if self._sel is not None:
            self._sel.close()
        self._wake_r.close()
        self._wake_w.close()

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc):
        self.stop()

    def stats(self) -> dict:
        """Counters for `coopctl status` (garbage, oversize, slow clients ... are counted here)."""
        return dict(
            self.counters,
            open_connections=len(self._conns),
            reply_buffer_bytes=self._buffered,
            reply_buffer_limit=self.max_reply_buffer_bytes,
        )

    def _ping(self, args: dict) -> dict:
        return {"protocol": PROTOCOL_VERSION, "commands": sorted(self.handlers), "pid": os.getpid()}

    def _bind(self) -> socket.socket:
        """Bind under a temporary name, set mode and group, then rename into place: the socket
        never exists at `path` with looser permissions."""
        if os.path.lexists(self.path):
            self._remove_stale()
        tmp = f"{self.path}.{os.getpid()}.tmp"
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        try:
            try:
                os.unlink(tmp)
            except FileNotFoundError:
                pass
            sock.bind(tmp)
            os.chmod(tmp, self.mode)
            if self.group is not None:
                os.chown(tmp, -1, self.group)
            sock.listen(LISTEN_BACKLOG)
            os.rename(tmp, self.path)
        except BaseException:
            sock.close()
            try:
                os.unlink(tmp)
            except FileNotFoundError:
                pass
            raise
        sock.setblocking(False)
        return sock

    def _remove_stale(self) -> None:
        if not stat.S_ISSOCK(os.lstat(self.path).st_mode):
            raise FileExistsError(f"{self.path} exists and is not a socket; refusing to replace it")
        probe = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        probe.settimeout(1.0)
        try:
            probe.connect(self.path)
        except OSError:
            os.unlink(self.path)
            log.info("removed stale control socket %s", self.path)
            return
        finally:
            probe.close()
        raise RuntimeError(f"another process is serving {self.path}; is coopd already running?")

    # -------------------------------------------------------------------------------- loop
    def _run(self) -> None:
        if self.on_thread_start is not None:
            try:
                self.on_thread_start()
            except Exception:
                log.exception("control thread start hook failed")
        while not self._stop.is_set():
            try:
                self._step()
            except Exception:  # never let one bad event end the control thread
                log.exception("control socket loop error (continuing)")
                self.counters["errors"] += 1
                time.sleep(0.01)

    def _step(self) -> None:
        now = time.monotonic()
        deadlines = [c.deadline for c in self._conns.values() if c.phase != "handling"]
        wait = max(0.0, min(deadlines) - now) if deadlines else 1.0
        if len(self._conns) >= self.max_clients:
            evictable_at = self._evictable_at()
            self._listen(evictable_at is not None and evictable_at <= now)
            if evictable_at is not None:
                wait = min(wait, max(0.0, evictable_at - now))
        else:
            self._listen(True)
        for key, events in self._sel.select(min(wait, 1.0)):
            if key.data == "listen":
                self._accept()
            elif key.data == "wake":
                self._drain_wake()
            else:
                conn = key.data
                if conn.sock.fileno() < 0:
                    continue
                if events & selectors.EVENT_READ and conn.phase == "read":
                    self._read(conn)
                elif events & selectors.EVENT_WRITE and conn.phase == "write":
                    self._write(conn)
        self._collect_replies()
        self._expire(time.monotonic())

    def _listen(self, on: bool) -> None:
        """Accept new connections only while a slot is free or can be freed; otherwise they wait
        in the kernel's backlog (nothing is refused that could be served a moment later)."""
        if on != self._accepting:
            if on:
                self._sel.register(self._listener, selectors.EVENT_READ, "listen")
            else:
                self._sel.unregister(self._listener)
            self._accepting = on

    def _evictable_at(self) -> float | None:
        """When a connection may be evicted to make room (None: none can be): the oldest one still
        sending its request, else the oldest reply still being read."""
        victim = self._victim()
        if victim is None:
            return None
        if victim.phase == "read":
            return victim.opened + self.evict_after_s
        return victim.replied + self.evict_reply_after_s

    def _victim(self) -> "_Conn | None":
        reading = [c for c in self._conns.values() if c.phase == "read"]
        if reading:
            return min(reading, key=lambda c: c.opened)
        writing = [c for c in self._conns.values() if c.phase == "write"]
        return min(writing, key=lambda c: c.replied) if writing else None

    def _wake(self) -> None:
        try:
            self._wake_w.send(b"x")
        except OSError:
            pass

    def _drain_wake(self) -> None:
        try:
            while self._wake_r.recv(4096):
                pass
        except OSError:
            pass

    def _accept(self) -> None:
        for _ in range(64):
            if len(self._conns) >= self.max_clients and not self._evict_one():
                return
            try:
                sock, _ = self._listener.accept()
            except (BlockingIOError, InterruptedError):
                return
            except OSError as e:  # EMFILE and friends: count, keep serving the ones we have
                self.counters["errors"] += 1
                log.warning("control socket accept failed: %s", e)
                return
            sock.setblocking(False)
            conn = _Conn(sock, self.timeout_s)
            conn.peer_uid = _peer_uid(sock)
            self._conns[sock.fileno()] = conn
            self._sel.register(sock, selectors.EVENT_READ, conn)
            self.counters["accepted"] += 1
            self._read(conn)  # coopctl sends at once: a complete request leaves the evictable set now

    def _evict_one(self) -> bool:
        """Drop the oldest connection still sending its request after evict_after_s (a slow or
        stuck client: coopctl sends its whole request right after connecting), else the oldest
        reply still unread after evict_reply_after_s (coopctl reads a 100 MiB map in a fraction)."""
        at = self._evictable_at()
        if at is None or at > time.monotonic():
            return False
        victim = self._victim()
        if victim.phase == "read":
            self.counters["evicted"] += 1
            self._send_now(victim.sock, error_reply("evicted", "connection dropped to make room for another"))
        else:
            self.counters["evicted_replies"] += 1
            self._log_cut(victim, "cut to make room for another client")
        self._close(victim)
        return True

    def _log_cut(self, conn: "_Conn", why: str) -> None:
        unsent = sum(len(p) for p in conn.out)
        log.warning(
            "control: a %d-byte reply to uid %d %s after %.1f s, %d bytes unread (%d reply timeouts, "
            "%d replies cut for room so far)",
            conn.charged,
            conn.peer_uid,
            why,
            time.monotonic() - conn.replied,
            unsent,
            self.counters["reply_timeouts"],
            self.counters["evicted_replies"],
        )

    def _read(self, conn: _Conn) -> None:
        want = LENGTH.size - len(conn.buf) if conn.need is None else conn.need - len(conn.buf)
        try:
            chunk = conn.sock.recv(min(max(want, 1), 65536))
        except (BlockingIOError, InterruptedError):
            return
        except OSError:
            self._close(conn)
            return
        if not chunk:
            self.counters["bad_requests"] += 1
            self._close(conn)
            return
        conn.buf += chunk
        if conn.need is None and len(conn.buf) >= LENGTH.size:
            (n,) = LENGTH.unpack_from(conn.buf)
            del conn.buf[: LENGTH.size]
            if n > self.max_request_bytes:
                self.counters["oversize"] += 1
                log.warning("control: refused a %d-byte request (limit %d)", n, self.max_request_bytes)
                self._reply(
                    conn, error_reply("too_large", f"request of {n} bytes exceeds {self.max_request_bytes}")
                )
                return
            if n == 0:
                self.counters["bad_requests"] += 1
                self._reply(conn, error_reply("bad_request", "empty request"))
                return
            conn.need = n
        if conn.need is not None and len(conn.buf) == conn.need:
            self._dispatch(conn)

    def _dispatch(self, conn: _Conn) -> None:
        try:
            request = _strict_json(bytes(conn.buf).decode("utf-8"))
        except (UnicodeDecodeError, ValueError, RecursionError):
            self.counters["bad_requests"] += 1
            self._reply(conn, error_reply("bad_request", "request is not UTF-8 JSON"))
            return
        conn.buf = bytearray()
        problem = _check_request(request)
        if problem:
            code, message = problem
            self.counters["bad_requests"] += 1
            self._reply(conn, error_reply(code, message))
            return
        cmd = request["cmd"]
        handler = self.handlers.get(cmd)
        if handler is None:
            self.counters["unknown_commands"] += 1
            self._reply(
                conn,
                error_reply(
                    "unknown_command",
                    f"unknown command {cmd[:40]!r}; known: {', '.join(sorted(self.handlers))}",
                ),
            )
            return
        conn.phase = "handling"
        self._sel.unregister(conn.sock)
        args = request.get("args") or {}
        pool = self._quick_pool if cmd in self.quick_commands else self._pool
        pool.submit(self._handle, conn, cmd, handler, args)

    def _handle(self, conn: _Conn, cmd: str, handler: Handler, args: dict) -> None:
        """Runs in a worker: the reply bytes go back to the loop thread."""
        t0 = time.monotonic()
        try:
            result = handler(args)
            if isinstance(result, BlobReply):
                head = encode_frame(
                    {
                        "v": PROTOCOL_VERSION,
                        "ok": True,
                        "result": result.result,
                        "blob_bytes": len(result.data),
                    }
                )
                reply = [head, result.data]
            else:
                reply = [encode_frame({"v": PROTOCOL_VERSION, "ok": True, "result": result})]
        except CommandFailed as e:
            reply = [error_reply("failed", str(e))]
        except Exception as e:
            self.counters["handler_errors"] += 1
            log.exception("control: command %s failed", cmd)
            reply = [error_reply("internal", f"{cmd} failed inside the daemon: {type(e).__name__}: {e}")]
        size = sum(len(p) for p in reply)
        log.debug(
            "control: %s from uid %d in %.1f ms, %d reply bytes", cmd, conn.peer_uid,
            1000 * (time.monotonic() - t0), size,
        )
        with self._done_lock:
            if len(reply) > 1 and self._buffered and self._buffered + size > self.max_reply_buffer_bytes:
                self.counters["refused_busy"] += 1
                busy = self._buffered
                reply = [error_reply(
                    "busy",
                    f"a {size}-byte reply does not fit next to the {busy} bytes other clients are still "
                    f"reading (limit {self.max_reply_buffer_bytes}); try again",
                )]
                size = len(reply[0])
            else:
                busy = 0
            conn.charged = size
            self._buffered += size
            self._done.append((conn, reply))
        if busy:
            n = self.counters["refused_busy"]
            if n in (1, 10, 100) or n % 1000 == 0:
                log.warning("control: refused a %s reply: %d reply bytes already queued for other "
                            "clients (limit %d; %d refused so far)", cmd, busy,
                            self.max_reply_buffer_bytes, n)
        self._wake()

    def _collect_replies(self) -> None:
        with self._done_lock:
            done, self._done = self._done, []
        for conn, reply in done:
            if conn.sock.fileno() < 0:
                self._uncharge(conn)
                continue
            conn.phase = "read"  # so _reply registers it
            self._sel.register(conn.sock, selectors.EVENT_READ, conn)
            self._reply(conn, reply, served=True)

    def _reply(self, conn: _Conn, data: "bytes | list", served: bool = False) -> None:
        """Queue a reply (bytes, or parts sent in order) under a deadline that progress does not move."""
        if served:
            self.counters["served"] += 1
        parts = [memoryview(p) for p in (data if isinstance(data, list) else [data])]
        size = sum(len(p) for p in parts)
        conn.phase = "write"
        conn.out = [p for p in parts if len(p)]
        conn.replied = time.monotonic()
        conn.deadline = conn.replied + self.timeout_s + size / self.min_reply_rate
        self._sel.modify(conn.sock, selectors.EVENT_WRITE, conn)
        self._write(conn)

    def _write(self, conn: _Conn) -> None:
        if not conn.out:
            self._close(conn)
            return
        try:
            sent = conn.sock.send(conn.out[0][: 1 << 20])
        except (BlockingIOError, InterruptedError):
            return
        except OSError:
            self._close(conn)
            return
        conn.out[0] = conn.out[0][sent:]
        if not len(conn.out[0]):
            conn.out.pop(0)
        if not conn.out:
            self._close(conn)

    def _expire(self, now: float) -> None:
        for conn in list(self._conns.values()):
            if conn.phase != "handling" and now > conn.deadline:
                if conn.phase == "read":
                    self.counters["timeouts"] += 1
                    self._send_now(
                        conn.sock, error_reply("timeout", f"request not complete within {self.timeout_s} s")
                    )
                else:
                    self.counters["reply_timeouts"] += 1
                    self._log_cut(conn, "not read by its deadline")
                self._close(conn)

    def _send_now(self, sock: socket.socket, data: bytes) -> None:
        """Best effort, never blocks: used for errors sent just before closing."""
        try:
            sock.send(data)
        except OSError:
            pass

    def _close(self, conn: _Conn) -> None:
        fd = conn.sock.fileno()
        if fd >= 0:
            self._conns.pop(fd, None)
            try:
                self._sel.unregister(conn.sock)
            except (KeyError, ValueError):
                pass
            conn.sock.close()
        conn.out = []
        self._uncharge(conn)

    def _uncharge(self, conn: _Conn) -> None:
        """Give the connection's reply bytes back to the reply buffer (once)."""
        if conn.charged:
            with self._done_lock:
                self._buffered -= conn.charged
                conn.charged = 0


def _refuse_constant(name: str):
    raise ValueError(f"{name} is not JSON")


def _finite_float(text: str) -> float:
    value = float(text)
    if not math.isfinite(value):
        raise ValueError(f"number {text[:20]} is out of range")
    return value


def _strict_json(text: str):
    """JSON as RFC 8259 has it: NaN, Infinity and numbers that overflow a float are refused (ValueError),
    so a handler never sees a value the reply encoder (allow_nan=False) cannot send back."""
    return json.loads(text, parse_constant=_refuse_constant, parse_float=_finite_float)


def _check_request(request) -> tuple[str, str] | None:
    if not isinstance(request, dict):
        return "bad_request", "request must be a JSON object"
    v = request.get("v")
    if type(v) is not int or v != PROTOCOL_VERSION:  # 1.0 and true compare equal to 1
        return "version", f"protocol version {v!r} not supported (this coopd speaks {PROTOCOL_VERSION})"
    cmd = request.get("cmd")
    if not isinstance(cmd, str) or not cmd:
        return "bad_request", "request needs a command name (cmd)"
    args = request.get("args", {})
    if args is not None and not isinstance(args, dict):
        return "bad_request", "args must be a JSON object"
    return None


def _peer_uid(sock: socket.socket) -> int:
    try:
        creds = sock.getsockopt(socket.SOL_SOCKET, socket.SO_PEERCRED, struct.calcsize("3i"))
        return struct.unpack("3i", creds)[1]
    except OSError:
        return -1


# ------------------------------------------------------------------------------------------ client
class ControlError(OSError):
    """coopctl could not get an answer; the message is meant for the operator. An OSError, so
    that coopctl reports it like any other I/O failure (one line; exit code 1, or 5 when
    DaemonUnreachable)."""


class DaemonUnreachable(ControlError):
    """No answer at all: the daemon is not running, its socket is not ours to use, or it is silent."""


class DaemonNotRunning(DaemonUnreachable):
    pass


class SocketAccessDenied(DaemonUnreachable):
    pass


class RemoteError(ControlError):
    """The daemon answered with an error reply."""

    def __init__(self, code: str, message: str):
        super().__init__(message)
        self.code = code


def request(
    path,
    cmd: str,
    args: dict | None = None,
    *,
    timeout_s: float = 10.0,
    max_reply_bytes: int = DEFAULT_MAX_REPLY,
    max_blob_bytes: int = 0,
) -> tuple[dict, bytes | None]:
    """Send one command to the daemon; returns (result, blob or None) or raises ControlError."""
    path = os.fspath(path)
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    sock.settimeout(timeout_s)
    try:
        try:
            _connect(sock, path, timeout_s)
        except FileNotFoundError:
            raise DaemonNotRunning(
                f"coopd is not running: no control socket at {path} "
                "(start it with `systemctl start coopd`, or point --socket at it)"
            ) from None
        except ConnectionRefusedError:
            raise DaemonNotRunning(
                f"coopd is not running: nothing listens on {path} "
                "(a stale socket: the daemon stopped or is still starting)"
            ) from None
        except PermissionError:
            raise SocketAccessDenied(
                f"permission denied on {path}: coopctl must run as a member of the "
                "daemon's group (e.g. `sudo usermod -aG coopd $USER`, then log in again) "
                "or as root"
            ) from None
        except OSError as e:
            if e.errno in (errno.ENOTSOCK, errno.ENOTDIR):
                raise DaemonNotRunning(f"{path} is not a coopd control socket") from None
            raise DaemonUnreachable(f"cannot connect to {path}: {e.strerror or e}") from None
        try:
            sock.sendall(encode_frame({"v": PROTOCOL_VERSION, "cmd": cmd, "args": args or {}}))
            head = _recv_exact(sock, LENGTH.size)
            (n,) = LENGTH.unpack(head)
            if n > max_reply_bytes:
                raise ControlError(f"reply of {n} bytes exceeds the limit of {max_reply_bytes}")
            reply = _strict_json(_recv_exact(sock, n).decode("utf-8"))
            if not isinstance(reply, dict) or reply.get("v") != PROTOCOL_VERSION:
                raise ControlError(
                    f"unexpected reply from {path} (not coopd control protocol v{PROTOCOL_VERSION})"
                )
            if not reply.get("ok"):
                raise RemoteError(str(reply.get("code", "")), str(reply.get("error", "unknown error")))
            blob = None
            result = reply.get("result") or {}
            if not isinstance(result, dict):
                raise ControlError(f"garbled reply from {path}: result is not a JSON object")
            if "blob_bytes" in reply:
                size = reply["blob_bytes"]
                if type(size) is not int:
                    raise ControlError(f"garbled reply from {path}: blob_bytes {size!r:.40} is no integer")
                if not 0 <= size <= max_blob_bytes:
                    raise ControlError(f"daemon sends {size} bytes, more than the limit of {max_blob_bytes}")
                blob = _recv_exact(sock, size)
            return result, blob
        except TimeoutError:
            raise DaemonUnreachable(f"coopd did not answer {cmd!r} within {timeout_s} s") from None
        except (ConnectionResetError, BrokenPipeError):
            raise ControlError(f"coopd closed the connection during {cmd!r}") from None
        except (ValueError, TypeError, RecursionError) as e:
            raise ControlError(f"garbled reply from {path}: {type(e).__name__}: {e}") from None
    finally:
        sock.close()


def _connect(sock: socket.socket, path: str, timeout_s: float) -> None:
    """connect(), waiting while the daemon's backlog is full (a unix socket then fails at once
    with EAGAIN instead of blocking, as soon as the socket has a timeout)."""
    deadline = time.monotonic() + timeout_s
    delay = 0.005
    while True:
        try:
            sock.connect(path)
            return
        except BlockingIOError:
            if time.monotonic() + delay > deadline:
                raise TimeoutError(f"the daemon's connection backlog stayed full for {timeout_s} s") from None
            time.sleep(delay)
            delay = min(delay * 2, 0.1)


def _recv_exact(sock: socket.socket, n: int) -> bytes:
    buf = bytearray()
    while len(buf) < n:
        chunk = sock.recv(min(n - len(buf), 1 << 20))
        if not chunk:
            raise ControlError(f"coopd closed the connection after {len(buf)} of {n} bytes")
        buf += chunk
    return bytes(buf)

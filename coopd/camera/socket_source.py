"""Camera socket client: reads framed z16 depth, validates it, keeps the newest, reconnects by itself."""

from __future__ import annotations

import contextlib
import errno
import logging
import os
import socket
import threading
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from .frame import DepthFrame
from .protocol import CLOCK_FC, FrameHeader, ProtocolError, header_length, parse_header
from .slot import LatestSlot

log = logging.getLogger("coopd.camera")

CAMERA_SOCKET_DIR = "/run/coopd-camera"
"""Where camera drivers put their sockets: made at boot by systemd/coopd.tmpfiles (root:coopd, mode
3770: group members create sockets there, only a socket's owner removes it), kept across restarts."""
DEFAULT_CAMERA_SOCKET = CAMERA_SOCKET_DIR + "/camera.sock"
RECV_POLL_S = 0.1
FUTURE_TOLERANCE_S = 1.0
"""A frame stamped more than this (FC seconds) after the FC's clock is from the future: dropped.
The same bound, in host seconds, applies to host-monotonic stamps against time.monotonic()."""


def explain_connect_failure(address: str, err: OSError) -> str:
    """What an operator should check when connecting to the camera driver failed, in one phrase."""
    if address.startswith("tcp:"):
        if err.errno == errno.ECONNREFUSED:
            return f"{err.strerror or err}: is the camera driver running and listening there?"
        return str(err)
    path = address[5:] if address.startswith("unix:") else address
    directory = os.path.dirname(path) or "."
    if err.errno == errno.ENOENT:
        if not os.path.isdir(directory):
            return (
                f"directory {directory} does not exist (for {CAMERA_SOCKET_DIR}: install "
                "systemd/coopd.tmpfiles as /etc/tmpfiles.d/coopd.conf and run systemd-tmpfiles --create)"
            )
        return "no socket there yet: is the camera driver running?"
    if err.errno == errno.ECONNREFUSED:
        return "the socket exists but nobody listens on it: the camera driver stopped or is restarting"
    if err.errno in (errno.EACCES, errno.EPERM):
        return (
            "permission denied: the socket must be group coopd and group-writable "
            "(run the driver in group coopd with umask 0007)"
        )
    return str(err)


def worth_a_line(count: int) -> bool:
    """Log the 1st, 10th, 100th and every 1000th of a repeated event: seen, never a flood."""
    return count in (1, 10, 100) or count % 1000 == 0


class FcClock(Protocol):
    """What the camera client needs from the vehicle link (coopd.vehicle.VehicleLink provides it)."""

    def fc_time_latest(self) -> float | None:
        """An FC time (seconds since its boot) that has surely passed, or None while unknown."""

    def fc_epoch(self) -> int:
        """Changes whenever the FC's time base restarted (a reboot)."""


@dataclass(frozen=True)
class SocketSourceConfig:
    """Where the driver listens and how patient to be with it."""

    address: str  # "/run/cam.sock", "unix:/run/cam.sock" or "tcp:127.0.0.1:5600"
    max_payload_bytes: int = 8 * 1024 * 1024
    connect_timeout_s: float = 1.0
    stall_timeout_s: float = 2.0  # no byte for this long on an open connection: reconnect
    frame_timeout_s: float = 5.0  # a started frame must complete within this (no byte-trickling driver)
    backoff_s: tuple[float, float] = (0.1, 2.0)
    relatch_after_s: float = 1.0  # every frame older than the reference for this long: take the new clock

    def __post_init__(self):
        if not isinstance(self.address, str) or not self.address:
            raise ValueError("camera address must be a unix socket path or tcp:host:port")
        if not (1 <= self.max_payload_bytes <= 256 * 1024 * 1024):
            raise ValueError("max_payload_bytes must be within 1 B..256 MiB")
        if not (
            0 < self.stall_timeout_s <= 60
            and 0 < self.connect_timeout_s <= 60
            and 0 < self.frame_timeout_s <= 600
            and 0 < self.relatch_after_s <= 60
        ):
            raise ValueError("camera timeouts must be within (0, 60] s")


class _Closed(Exception):
    """The connection ended (EOF, reset, stall or stop); `reason` is a counter key."""

    def __init__(self, reason: str):
        super().__init__(reason)
        self.reason = reason


class SocketDepthSource:
    """One thread per camera: connect, read frame after frame into a LatestSlot, reconnect with backoff.

    Frames stamped in host-monotonic time (header `clock` = "monotonic") are converted to FC time
    with host_to_fc (the vehicle link's clock fit); while it has none they are dropped and counted.

    Frame times must increase (in the driver's own time domain). The reference they are checked
    against (the newest accepted stamp) never latches: a frame stamped after the FC's clock now is
    dropped without moving it, an FC reboot (fc_epoch changes) resets it for FC-time stamps, and
    frames all older than it for relatch_after_s make the newest of them the reference (a driver
    whose clock restarted without reconnecting).
    """

    def __init__(
        self,
        config: SocketSourceConfig,
        slot: LatestSlot | None = None,
        fc: FcClock | None = None,
        host_to_fc: Callable[[float], float | None] | None = None,
    ):
        self.config = config
        self.fc = fc
        self.host_to_fc = host_to_fc
        self.slot: LatestSlot[DepthFrame] = slot if slot is not None else LatestSlot()
        self.counters: Counter = Counter()
        self.connected = False
        self.last_frame_local: float | None = None
        self.native_id: int | None = None
        self._last_seq: int | None = None
        self._last_t_us: int | None = None
        self._last_clock = CLOCK_FC  # the time domain of _last_t_us
        self._behind_since: float | None = None  # local time of the first of consecutive older frames
        self._fc_epoch = fc.fc_epoch() if fc is not None else 0
        self._sock: socket.socket | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    # -- lifecycle ------------------------------------------------------------------------------

    def start(self) -> None:
        if self._thread is None:
            self._stop.clear()
            self._thread = threading.Thread(target=self.run, name="coopd-camera", daemon=True)
            self._thread.start()

    def stop(self, timeout: float = 2.0) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout)
            self._thread = None

    def run(self) -> None:
        """Connect/read/reconnect until stopped; every failure is counted, none escapes."""
        self.native_id = threading.get_native_id()
        backoff = self.config.backoff_s[0]
        while not self._stop.is_set():
            try:
                self._connect()
            except OSError as e:
                self.counters["connect_failures"] += 1
                if worth_a_line(self.counters["connect_failures"]):
                    log.warning(
                        "camera %s not reachable (%s); retrying with backoff up to %.1f s (%d failures)",
                        self.config.address,
                        explain_connect_failure(self.config.address, e),
                        self.config.backoff_s[1],
                        self.counters["connect_failures"],
                    )
                self._stop.wait(backoff)
                backoff = min(backoff * 2, self.config.backoff_s[1])
                continue
            frames_before = self.counters["frames"]
            reason = self._read_frames()
            self._disconnect(reason)
            if self.counters["frames"] > frames_before:
                backoff = self.config.backoff_s[0]
            else:
                self._stop.wait(backoff)
                backoff = min(backoff * 2, self.config.backoff_s[1])

    def _connect(self) -> None:
        addr = self.config.address
        if addr.startswith("tcp:"):
            host, _, port = addr[4:].rpartition(":")
            if not port.isdigit():
                raise OSError(f"bad tcp address {addr!r}")
            s = socket.create_connection((host, int(port)), timeout=self.config.connect_timeout_s)
        else:
            path = addr[5:] if addr.startswith("unix:") else addr
            s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
            s.settimeout(self.config.connect_timeout_s)
            try:
                s.connect(path)
            except OSError:
                s.close()
                raise
        s.settimeout(RECV_POLL_S)
        self._sock = s
        self.connected = True
        self.counters["connects"] += 1
        self._last_seq = self._last_t_us = self._behind_since = None  # a restarted driver restarts both
        log.info("camera connected: %s (connection #%d)", addr, self.counters["connects"])

    def _disconnect(self, reason: str) -> None:
        if self._sock is not None:
            with contextlib.suppress(OSError):
                self._sock.close()
        self._sock = None
        self.connected = False
        self.counters["disconnect_" + reason] += 1
        if reason != "stopped":
            log.warning(
                "camera %s disconnected (%s) after %d frames in total; reconnecting",
                self.config.address,
                reason,
                self.counters["frames"],
            )

    # -- reading --------------------------------------------------------------------------------

    def _read_frames(self) -> str:
        """Read until the connection must end; returns the reason."""
        try:
            while True:
                self._read_one()
        except _Closed as c:
            return c.reason
        except ProtocolError as e:
            self.counters["protocol_" + e.reason] += 1
            log.warning("camera %s broke the protocol (%s); dropping the connection", self.config.address, e)
            return "protocol_error"
        except Exception:  # a bug of ours must not kill the camera thread: count, log, reconnect
            self.counters["internal_errors"] += 1
            if self.counters["internal_errors"] <= 3:
                log.exception("camera %s: unexpected error while reading; reconnecting", self.config.address)
            return "internal_error"

    def _recv_exact(self, buf: memoryview, deadline: float = float("inf")) -> None:
        """Fill buf completely; a gap of stall_timeout_s without bytes, EOF or stop ends the connection."""
        got, last_byte = 0, time.monotonic()
        while got < len(buf):
            if self._stop.is_set():
                raise _Closed("stopped")
            try:
                k = self._sock.recv_into(buf[got:], len(buf) - got)
            except TimeoutError:
                if time.monotonic() - last_byte > self.config.stall_timeout_s:
                    raise _Closed("stall") from None
                continue
            except InterruptedError:
                continue
            except OSError:
                raise _Closed("reset") from None
            if k == 0:
                raise _Closed("eof")
            got += k
            last_byte = time.monotonic()
            if last_byte > deadline:
                raise _Closed("slow_frame")

    def _read_one(self) -> None:
        prefix = bytearray(4)
        self._recv_exact(memoryview(prefix))
        deadline = time.monotonic() + self.config.frame_timeout_s
        raw = bytearray(header_length(bytes(prefix)))
        self._recv_exact(memoryview(raw), deadline)
        header = parse_header(bytes(raw), self.config.max_payload_bytes)
        payload = np.empty(header.n // 2, dtype="<u2")  # bounded by max_payload_bytes, checked above
        self._recv_exact(memoryview(payload).cast("B"), deadline)
        now = time.monotonic()
        problem = header.intrinsics.implausible()
        if problem is not None:  # a misconfigured driver, not a broken stream: drop the frame, stay
            self.counters["dropped_implausible_intrinsics"] += 1
            if worth_a_line(self.counters["dropped_implausible_intrinsics"]):
                log.warning("camera %s: frame %d dropped, implausible intrinsics: %s (%d dropped so far)",
                            self.config.address, header.seq, problem,
                            self.counters["dropped_implausible_intrinsics"])
            return
        t_fc = self._fc_time_of(header, now)
        if t_fc is None:
            return
        if self._last_seq is not None and header.seq != self._last_seq + 1:
            self.counters["seq_gaps"] += 1
        self._last_seq, self._last_t_us, self._last_clock = header.seq, header.t_us, header.clock
        # Wire order is little-endian; astype is a no-op on little-endian hosts, a swap elsewhere.
        depth = payload.reshape(header.intrinsics.height, header.intrinsics.width).astype(
            np.uint16, copy=False
        )
        frame = DepthFrame(header.seq, t_fc, depth, header.intrinsics, header.min_m, header.max_m, now)
        self.counters["frames"] += 1
        self.last_frame_local = now
        self.slot.put(frame)

    def _fc_time_of(self, header: FrameHeader, now: float) -> float | None:
        """The frame's FC time, or None (counted) if its stamp is from the future, not increasing, or
        in host time while the FC clock fit is unknown."""
        t_us, fc_domain = header.t_us, header.clock == CLOCK_FC
        if header.clock != self._last_clock and self._last_t_us is not None:
            self._reset_reference("clock_domain_changed", t_us)
        if self.fc is not None:
            epoch = self.fc.fc_epoch()
            if epoch != self._fc_epoch:
                self._fc_epoch = epoch
                if self._last_t_us is not None and fc_domain:  # host stamps do not restart with the FC
                    self._reset_reference("fc_reboot", t_us)
        if fc_domain:
            t_fc = t_us * 1e-6
        elif t_us * 1e-6 > now + FUTURE_TOLERANCE_S:
            return self._drop_future(t_us * 1e-6 - now, "host")
        else:
            t_fc = None if self.host_to_fc is None else self.host_to_fc(t_us * 1e-6)
            if t_fc is None:
                self.counters["dropped_no_fc_clock"] += 1
                if worth_a_line(self.counters["dropped_no_fc_clock"]):
                    log.warning("camera frame in host time dropped: no FC clock fit yet (%d so far)",
                                self.counters["dropped_no_fc_clock"])
                return None
        fc_now = None if self.fc is None else self.fc.fc_time_latest()
        if fc_now is not None and t_fc > fc_now + FUTURE_TOLERANCE_S:
            return self._drop_future(t_fc - fc_now, "FC")
        if self._last_t_us is not None and t_us <= self._last_t_us:
            if self._behind_since is None:
                self._behind_since = now
            if now - self._behind_since < self.config.relatch_after_s:
                self.counters["dropped_timestamp_not_increasing"] += 1
                return None
            self._reset_reference("stamps_went_back", t_us)
        self._behind_since = None
        return t_fc

    def _drop_future(self, ahead_s: float, clock: str) -> None:
        self.counters["dropped_future_timestamp"] += 1
        if worth_a_line(self.counters["dropped_future_timestamp"]):
            log.warning(
                "camera frame stamped %.3f s ahead of the %s clock: dropped (%d so far)",
                ahead_s,
                clock,
                self.counters["dropped_future_timestamp"],
            )

    def _reset_reference(self, reason: str, t_us: int) -> None:
        """Forget the newest accepted stamp: the FC or the driver restarted its clock."""
        self.counters["time_reference_resets_" + reason] += 1
        log.warning(
            "camera time reference reset (%s): stamps continue at %.3f s after %.3f s",
            reason.replace("_", " "),
            t_us * 1e-6,
            (self._last_t_us or 0) * 1e-6,
        )
        self._last_t_us = self._behind_since = None

    def status(self) -> dict:
        """Snapshot for status reports."""
        age = None if self.last_frame_local is None else round(time.monotonic() - self.last_frame_local, 3)
        c = dict(self.counters)
        c["slot_dropped"] = self.slot.dropped
        return {
            "address": self.config.address,
            "connected": self.connected,
            "last_frame_age_s": age,
            "thread_native_id": self.native_id,
            "counters": c,
        }

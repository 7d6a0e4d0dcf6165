"""sd_notify for Type=notify: READY=1, STATUS=..., WATCHDOG=1, STOPPING=1.

The daemon sends the datagram itself to $NOTIFY_SOCKET (a path, or "@name" for the abstract
namespace), which is all sd_notify(3) does, but never blocks: a full notify queue (PID 1 busy)
drops and counts the message. systemd-python's `systemd.daemon.notify` is not the default even when
installed: libsystemd's sd_notify blocks on a full queue and systemd-python calls it holding the
GIL, so one watchdog ping would stop every thread of the daemon until PID 1 reads its socket
(tests/daemon/test_notify.py reproduces it). Backend "systemd" stays available as an explicit choice.
Without NOTIFY_SOCKET (not started by systemd) every call is a no-op.

The watchdog is fed by WatchdogPinger at half of $WATCHDOG_USEC, and only while the daemon's
health check passes: a hung stage stops the pings and systemd restarts the service.
"""

import logging
import os
import socket
import threading
import time
from collections.abc import Callable

log = logging.getLogger("coopd.daemon")


def _load_systemd():
    try:
        from systemd import daemon  # systemd-python, optional extra "systemd"
    except ImportError:
        return None
    return daemon


class Notifier:
    """Sends sd_notify messages; backend "socket" (never blocks) or "systemd" (systemd-python)."""

    def __init__(self, backend: str = "socket", environ=None):
        env = os.environ if environ is None else environ
        self.address = env.get("NOTIFY_SOCKET") or None
        self._watchdog_usec = env.get("WATCHDOG_USEC")
        self._watchdog_pid = env.get("WATCHDOG_PID")
        if backend not in ("systemd", "socket"):
            raise ValueError(f"unknown notify backend {backend!r}")
        lib = _load_systemd() if backend == "systemd" else None
        if backend == "systemd" and lib is None:
            raise RuntimeError("systemd-python is not installed")
        self._lib = lib
        self.backend = "systemd-python" if lib is not None else "socket"
        self._sock: socket.socket | None = None
        self.dropped = 0
        """Messages dropped because the notify queue was full (the socket backend never blocks)."""
        self._lock = threading.Lock()
        self._warned = False
        self.sent = 0
        self.failed = 0

    @property
    def enabled(self) -> bool:
        return self.address is not None

    def notify(self, *fields: str) -> bool:
        """Send one message of KEY=value fields; True if it went out (False: no-op or error)."""
        if not self.enabled:
            return False
        message = "\n".join(fields)
        with self._lock:
            try:
                if self._lib is not None:
                    ok = bool(self._lib.notify(message))
                else:
                    ok = self._send(message.encode())
            except OSError as e:
                ok = False
                if not self._warned:
                    log.warning("sd_notify to %s failed: %s", self.address, e)
                    self._warned = True
            if ok:
                self.sent += 1
            else:
                self.failed += 1
            return ok

    def _send(self, data: bytes) -> bool:
        address = self.address
        if address.startswith("@"):
            address = "\0" + address[1:]
        elif not address.startswith("/"):
            raise OSError(f"unsupported NOTIFY_SOCKET address {address!r}")
        if self._sock is None:
            self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)
        try:
            # MSG_DONTWAIT: a full notify queue must never stall the caller (the watchdog pinger
            # or the main loop); the message is dropped and counted instead.
            return self._sock.sendto(data, socket.MSG_DONTWAIT, address) == len(data)
        except BlockingIOError:
            self.dropped += 1
            return False

    def ready(self, status: str | None = None) -> bool:
        fields = ["READY=1"] + ([f"STATUS={_one_line(status)}"] if status else [])
        return self.notify(*fields)

    def status(self, text: str) -> bool:
        return self.notify(f"STATUS={_one_line(text)}")

    def watchdog(self) -> bool:
        return self.notify("WATCHDOG=1")

    def stopping(self, status: str | None = None) -> bool:
        fields = ["STOPPING=1"] + ([f"STATUS={_one_line(status)}"] if status else [])
        return self.notify(*fields)

    def extend_timeout(self, seconds: float) -> bool:
        """Ask for more start/stop time (e.g. while numba compiles on a first start)."""
        return self.notify(f"EXTEND_TIMEOUT_USEC={int(seconds * 1e6)}")

    def watchdog_interval(self) -> float | None:
        """Seconds between WATCHDOG=1 pings (half of WATCHDOG_USEC), None if no watchdog for us."""
        if not self.enabled or not self._watchdog_usec:
            return None
        if self._watchdog_pid and self._watchdog_pid != str(os.getpid()):
            return None
        try:
            usec = int(self._watchdog_usec)
        except ValueError:
            return None
        return usec / 2e6 if usec > 0 else None

    def close(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None


def _one_line(text: str) -> str:
    return " ".join(str(text).split())[:400]


class WatchdogPinger:
    """A thread sending WATCHDOG=1 every `interval` seconds while `healthy()` returns True."""

    def __init__(
        self, notifier: Notifier, healthy: Callable[[], bool] = lambda: True, interval: float | None = None
    ):
        self.notifier = notifier
        self.healthy = healthy
        self.interval = interval if interval is not None else notifier.watchdog_interval()
        self.pings = 0
        self.withheld = 0
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def start(self) -> "WatchdogPinger":
        """Start pinging; does nothing when systemd asked for no watchdog."""
        if self.interval is None:
            return self
        self._thread = threading.Thread(target=self._run, name="coopd-watchdog", daemon=True)
        self._thread.start()
        log.info("watchdog: pinging every %.2f s while healthy", self.interval)
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5)

    def _run(self) -> None:
        next_at = time.monotonic()
        while not self._stop.is_set():
            try:
                ok = bool(self.healthy())
            except Exception:
                log.exception("watchdog health check raised")
                ok = False
            if ok:
                self.notifier.watchdog()
                self.pings += 1
            else:
                self.withheld += 1
                if self.withheld == 1 or self.withheld % 20 == 0:
                    log.error(
                        "watchdog: health check failed, withholding WATCHDOG=1 (%d times)", self.withheld
                    )
            next_at += self.interval
            now = time.monotonic()
            if next_at < now:  # fell behind (suspend, overload): don't burst, restart the cadence
                next_at = now + self.interval
            self._stop.wait(next_at - now)

"""sd_notify: a test binds its own NOTIFY_SOCKET (path and abstract) and reads what coopd sends."""

import os
import queue
import shutil
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import pytest

from coopd.daemon import notify
from coopd.daemon.notify import Notifier, WatchdogPinger

BACKENDS = ["socket"] + (["systemd"] if notify._load_systemd() is not None else [])


@pytest.fixture(params=["path", "abstract"])
def notify_socket(request, monkeypatch):
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    d = None
    if request.param == "path":
        d = tempfile.mkdtemp(prefix="coopd-notify-", dir="/tmp")
        address = os.path.join(d, "notify")
        sock.bind(address)
    else:
        name = f"coopd-test-notify-{os.getpid()}-{time.monotonic_ns()}"
        sock.bind("\0" + name)
        address = "@" + name
    sock.settimeout(2.0)
    monkeypatch.setenv("NOTIFY_SOCKET", address)
    monkeypatch.delenv("WATCHDOG_PID", raising=False)
    monkeypatch.delenv("WATCHDOG_USEC", raising=False)
    yield sock
    sock.close()
    if d:
        shutil.rmtree(d)


def recv_all(sock, quiet=0.3) -> list[tuple[float, str]]:
    out = []
    sock.settimeout(quiet)
    while True:
        try:
            data = sock.recv(4096)
        except TimeoutError:
            return out
        out.append((time.monotonic(), data.decode()))


@pytest.mark.parametrize("backend", BACKENDS)
def test_ready_status_stopping(notify_socket, backend):
    n = Notifier(backend)
    assert n.enabled
    assert n.ready("mapping at 0.1 m\nsecond line")
    assert notify_socket.recv(4096) == b"READY=1\nSTATUS=mapping at 0.1 m second line"
    assert n.status("3 peers, 2 merges")
    assert notify_socket.recv(4096) == b"STATUS=3 peers, 2 merges"
    assert n.extend_timeout(30)
    assert notify_socket.recv(4096) == b"EXTEND_TIMEOUT_USEC=30000000"
    assert n.stopping("checkpointing")
    assert notify_socket.recv(4096) == b"STOPPING=1\nSTATUS=checkpointing"
    assert n.sent == 4


@pytest.mark.parametrize("backend", BACKENDS)
def test_watchdog_at_half_of_watchdog_usec(notify_socket, backend, monkeypatch):
    monkeypatch.setenv("WATCHDOG_USEC", "200000")
    monkeypatch.setenv("WATCHDOG_PID", str(os.getpid()))
    n = Notifier(backend)
    assert n.watchdog_interval() == pytest.approx(0.1)
    msgs = []
    receiver = threading.Thread(target=lambda: msgs.extend(recv_all(notify_socket, quiet=0.3)))
    receiver.start()  # records arrival times as they happen
    pinger = WatchdogPinger(n).start()
    time.sleep(1.0)
    pinger.stop()
    receiver.join()
    assert all(m == "WATCHDOG=1" for _, m in msgs)
    assert 8 <= len(msgs) <= 12, len(msgs)
    gaps = [b[0] - a[0] for a, b in zip(msgs, msgs[1:], strict=False)]
    mean = sum(gaps) / len(gaps)
    assert 0.08 <= mean <= 0.12, mean


def test_unhealthy_daemon_gets_no_watchdog(notify_socket, monkeypatch):
    monkeypatch.setenv("WATCHDOG_USEC", "100000")
    healthy = {"ok": True}
    n = Notifier("socket")
    pinger = WatchdogPinger(n, healthy=lambda: healthy["ok"]).start()
    time.sleep(0.3)
    healthy["ok"] = False
    time.sleep(0.05)
    recv_all(notify_socket, quiet=0.05)
    time.sleep(0.5)
    late = recv_all(notify_socket, quiet=0.05)
    pinger.stop()
    assert late == [] and pinger.withheld >= 5 and pinger.pings >= 4


def test_watchdog_for_another_pid_or_absent(notify_socket, monkeypatch):
    monkeypatch.setenv("WATCHDOG_USEC", "100000")
    monkeypatch.setenv("WATCHDOG_PID", "1")
    assert Notifier("socket").watchdog_interval() is None
    monkeypatch.delenv("WATCHDOG_USEC")
    assert Notifier("socket").watchdog_interval() is None
    assert WatchdogPinger(Notifier("socket")).start().interval is None


@pytest.mark.parametrize("backend", BACKENDS)
def test_no_notify_socket_is_a_no_op(backend, monkeypatch):
    monkeypatch.delenv("NOTIFY_SOCKET", raising=False)
    n = Notifier(backend)
    assert not n.enabled and not n.ready("x") and not n.watchdog()
    assert n.watchdog_interval() is None and n.sent == 0 and n.failed == 0


def test_vanished_notify_socket_is_reported_not_fatal(monkeypatch, caplog):
    monkeypatch.setenv("NOTIFY_SOCKET", "/nonexistent/coopd/notify")
    n = Notifier("socket")
    assert n.ready() is False and n.watchdog() is False
    assert n.failed == 2
    assert "sd_notify" in caplog.text


# A process whose notify queue is full (PID 1 not reading): one notify from a side thread, then the
# main thread must still run. The receiving socket is never read; the queue fills in a few datagrams.
FULL_QUEUE_PROBE = """
import os, socket, sys, tempfile, threading, time
from coopd.daemon.notify import Notifier
path = os.path.join(tempfile.mkdtemp(prefix="coopd-notify-"), "notify")
deaf = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
deaf.bind(path)
filler = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
for _ in range(100000):
    try:
        filler.sendto(b"X=1", socket.MSG_DONTWAIT, path)
    except BlockingIOError:
        break
os.environ["NOTIFY_SOCKET"] = path  # libsystemd reads the environment
notifier = Notifier(sys.argv[1])
print("probe started", flush=True)
threading.Thread(target=notifier.watchdog, daemon=True).start()
time.sleep(0.5)
print("main thread runs, dropped", notifier.dropped, flush=True)
os._exit(0)
"""


PROBE_START_S = 60.0
"""How long the probe may take to import coopd and fill the queue on a loaded machine."""
FROZEN_S = 10.0
"""The probe's main thread prints 0.5 s after it starts the notify thread: silent this long, it froze."""


def _full_queue_probe(backend: str) -> str:
    """What FULL_QUEUE_PROBE printed after its start line; empty when the process froze (nothing within
    FROZEN_S of the start line: it is killed)."""
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[2])}
    proc = subprocess.Popen([sys.executable, "-c", FULL_QUEUE_PROBE, backend], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=env)
    lines: queue.Queue = queue.Queue()
    reader = threading.Thread(target=lambda: [lines.put(line) for line in proc.stdout], daemon=True)
    reader.start()
    try:
        try:
            started = lines.get(timeout=PROBE_START_S)
        except queue.Empty:
            started = None
        if started != "probe started\n":
            proc.kill()
            proc.wait(10)
            pytest.fail(f"the probe did not start: {started!r}, {proc.stderr.read()}")
        try:
            first = lines.get(timeout=FROZEN_S)
        except queue.Empty:
            return ""
        assert proc.wait(timeout=10) == 0, proc.stderr.read()
        reader.join(10)
        return first + "".join(lines.get() for _ in range(lines.qsize()))
    finally:
        if proc.poll() is None:
            proc.kill()
        proc.wait(10)


def test_full_notify_queue_drops_the_message_and_never_stops_the_daemon():
    assert _full_queue_probe("socket") == "main thread runs, dropped 1\n"


@pytest.mark.skipif(notify._load_systemd() is None, reason="systemd-python not installed")
def test_systemd_python_notify_on_a_full_queue_stops_every_thread():
    """Why the daemon uses its own backend: libsystemd blocks and systemd-python holds the GIL meanwhile.
    If this fails, a newer systemd-python releases the GIL and could become the default again."""
    assert _full_queue_probe("systemd") == ""

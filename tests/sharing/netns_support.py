"""Multi-host test support: a switch namespace with a bridge and one namespace per host (veth,
10.213.1.0/24 addresses that exist only inside the test's namespaces), or loopback addresses
when namespaces are unavailable; plus sharing_node processes driven over pipes."""

import json
import os
import queue
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent.parent
PYTHON = sys.executable
SUBNET = "10.213.1"


def _ip(*args, check=True) -> subprocess.CompletedProcess:
    return subprocess.run(["ip", *args], capture_output=True, text=True, timeout=10, check=check)


def netns_unavailable_reason() -> str | None:
    """None if this process can create network namespaces, else why not."""
    if os.environ.get("COOPD_TEST_NO_NETNS"):
        return "disabled by COOPD_TEST_NO_NETNS"
    if os.geteuid() != 0:
        return "not root"
    if shutil.which("ip") is None:
        return "iproute2 'ip' not found"
    name = f"coopdt-{os.getpid()}-probe"
    try:
        r = _ip("netns", "add", name, check=False)
        if r.returncode != 0:
            return f"ip netns add failed: {r.stderr.strip()}"
        _ip("netns", "del", name, check=False)
    except (OSError, subprocess.SubprocessError) as e:
        return f"ip netns unusable: {e}"
    return None


class NetnsLab:
    """Namespaces coopdt-<pid>-<n>-{sw,h1,h2,...}: hosts on one bridge; removed by cleanup()."""

    mode = "netns"

    def __init__(self):
        self.prefix = f"coopdt-{os.getpid()}-{int(time.monotonic() * 1000) % 100000}"
        self.switch = f"{self.prefix}-sw"
        self.namespaces: list[str] = []
        self.hosts: dict[int, str] = {}
        _ip("netns", "add", self.switch)
        self.namespaces.append(self.switch)
        _ip("-n", self.switch, "link", "add", "br0", "type", "bridge")
        _ip("-n", self.switch, "link", "set", "br0", "up")

    def add_host(self, i: int) -> str:
        """Namespace for host i with address 10.213.1.i on the bridge; returns the address."""
        ns = f"{self.prefix}-h{i}"
        _ip("netns", "add", ns)
        self.namespaces.append(ns)
        _ip("-n", self.switch, "link", "add", f"p{i}", "type", "veth", "peer", "name", "eth0", "netns", ns)
        _ip("-n", self.switch, "link", "set", f"p{i}", "master", "br0", "up")
        _ip("-n", ns, "addr", "add", f"{SUBNET}.{i}/24", "dev", "eth0")
        _ip("-n", ns, "link", "set", "eth0", "up")
        _ip("-n", ns, "link", "set", "lo", "up")
        self.hosts[i] = ns
        return f"{SUBNET}.{i}"

    def address(self, i: int) -> str:
        return f"{SUBNET}.{i}"

    def range_spec(self, n: int) -> str:
        return f"{SUBNET}.1-{SUBNET}.{n}"

    def command(self, i: int, argv: list[str]) -> list[str]:
        return ["ip", "netns", "exec", self.hosts[i], *argv]

    def link(self, i: int, up: bool) -> None:
        """Cut or restore host i's cable (its port on the switch)."""
        _ip("-n", self.switch, "link", "set", f"p{i}", "up" if up else "down")

    def shape(self, i: int, rate: str, burst: str = "32kb", latency: str = "50ms") -> None:
        """tc tbf on host i's egress (eth0) and on its switch port (traffic towards host i)."""
        for ns, dev in ((self.hosts[i], "eth0"), (self.switch, f"p{i}")):
            subprocess.run(["ip", "netns", "exec", ns, "tc", "qdisc", "replace", "dev", dev, "root", "tbf",
                            "rate", rate, "burst", burst, "latency", latency],
                           check=True, capture_output=True, timeout=10)

    def cleanup(self) -> None:
        for ns in reversed(self.namespaces):
            _ip("netns", "del", ns, check=False)
        self.namespaces.clear()


class LoopbackLab:
    """The same interface on loopback: host i is 127.<a>.<b>.i, one shared port."""

    mode = "loopback"

    def __init__(self):
        pid = os.getpid()
        self.base = f"127.{100 + pid % 100}.{pid // 100 % 250 + 1}"
        self.hosts: dict[int, str] = {}

    def add_host(self, i: int) -> str:
        self.hosts[i] = self.address(i)
        return self.hosts[i]

    def address(self, i: int) -> str:
        return f"{self.base}.{i}"

    def range_spec(self, n: int) -> str:
        return f"{self.base}.1-{self.base}.{n}"

    def command(self, i: int, argv: list[str]) -> list[str]:
        return argv

    def cleanup(self) -> None:
        pass


class Node:
    """A sharing_node.py process: start, send commands, read JSON status, kill."""

    def __init__(self, lab, i: int, vid: int, port: int, peers: str, *extra: str):
        self.lab, self.i, self.vid = lab, i, vid
        env = dict(os.environ, PYTHONPATH=f"{ROOT}{os.pathsep}{HERE}")
        argv = [PYTHON, str(HERE / "sharing_node.py"), "--vid", str(vid), "--host", lab.address(i),
                "--port", str(port), "--peers", peers, *extra]
        self.log_path = Path(os.environ.get("TMPDIR", "/tmp")) / f"coopdt-{os.getpid()}-node{vid}-{i}.log"
        self._log = open(self.log_path, "a")  # noqa: SIM115 - closed in stop()
        self.proc = subprocess.Popen(lab.command(i, argv), stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                     stderr=self._log, text=True, env=env)
        self._lines: queue.Queue = queue.Queue()
        threading.Thread(target=self._read, daemon=True).start()
        first = self._next(15)
        if not first.startswith("ready"):
            raise RuntimeError(f"node {vid} did not start: {first!r}; log {self.log_path}")

    def _read(self) -> None:
        for line in self.proc.stdout:
            self._lines.put(line.strip())
        self._lines.put("")

    def _next(self, timeout: float) -> str:
        try:
            return self._lines.get(timeout=timeout)
        except queue.Empty:
            raise TimeoutError(f"node {self.vid} silent for {timeout} s; log {self.log_path}") from None

    def _cmd(self, line: str) -> str:
        self.proc.stdin.write(line + "\n")
        self.proc.stdin.flush()
        return self._next(10)

    def publish(self, version: int, size: int) -> None:
        assert self._cmd(f"publish {version} {size}") == "ok"

    def status(self) -> dict:
        return json.loads(self._cmd("status"))

    def rss_kb(self) -> dict:
        """{'VmHWM': peak kB, 'VmRSS': current kB} of the node process."""
        return json.loads(self._cmd("rss"))

    def received(self) -> dict:
        return {int(k): v for k, v in self.status()["received"].items()}

    def kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
        self.proc.wait(10)
        self._log.close()

    def stop(self) -> None:
        if self.proc.poll() is None:
            try:
                self.proc.stdin.write("quit\n")
                self.proc.stdin.flush()
                self.proc.wait(10)
            except (OSError, subprocess.TimeoutExpired):
                self.proc.kill()
                self.proc.wait(10)
        if not self._log.closed:
            self._log.close()

    def log_text(self) -> str:
        return self.log_path.read_text() if self.log_path.exists() else ""

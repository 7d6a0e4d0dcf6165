"""A virtual radio network for swarm tests and the demo: one Linux network namespace per drone on a
bridge (veth cables that can be unplugged and shaped), or loopback addresses when namespaces are
unavailable (not root, no iproute2). Only addresses this module creates are ever used.

    lab = NetnsLab("coopd-demo", "10.214.1"); addr = lab.add_host(1); lab.attach_root()
    subprocess.Popen(lab.command(1, ["coopd", ...])); lab.link(1, up=False); lab.cleanup()

Namespace names carry the creating process id, so namespaces left behind by a process that was
killed -9 are found and removed by `remove_stale()`.
"""

import os
import re
import shutil
import subprocess

ROOT_HOST = 254
"""Host number of the root namespace's own address on the bridge (the simulator's side)."""


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
    name = f"coopd-{os.getpid()}-probe"
    try:
        r = _ip("netns", "add", name, check=False)
        if r.returncode != 0:
            return f"ip netns add failed: {r.stderr.strip()}"
        _ip("netns", "del", name, check=False)
    except (OSError, subprocess.SubprocessError) as e:
        return f"ip netns unusable: {e}"
    return None


def remove_stale(tag: str) -> list[str]:
    """Delete namespaces named <tag>-<pid>-... whose creating process is gone; returns their names."""
    try:
        listing = _ip("netns", "list", check=False).stdout
    except (OSError, subprocess.SubprocessError):
        return []
    removed = []
    for line in listing.splitlines():
        name = line.split()[0] if line.split() else ""
        m = re.fullmatch(rf"{re.escape(tag)}-(\d+)-.*", name)
        if m and not os.path.exists(f"/proc/{m.group(1)}"):
            _ip("netns", "del", name, check=False)
            removed.append(name)
    return removed


class NetnsLab:
    """Namespaces <tag>-<pid>-<n>-{sw,h1,h2,...}: hosts on one bridge in the switch namespace,
    host i at <subnet>.i on its eth0; removed by cleanup()."""

    mode = "netns"

    def __init__(self, tag: str = "coopdt", subnet: str = "10.213.1"):
        self.subnet = subnet
        self.prefix = f"{tag}-{os.getpid()}-{id(self) % 100000}"
        self.switch = f"{self.prefix}-sw"
        self.namespaces: list[str] = []
        self.hosts: dict[int, str] = {}
        self.root_link: str | None = None
        _ip("netns", "add", self.switch)
        self.namespaces.append(self.switch)
        _ip("-n", self.switch, "link", "add", "br0", "type", "bridge")
        _ip("-n", self.switch, "link", "set", "br0", "up")

    def add_host(self, i: int) -> str:
        """Namespace for host i (1..253) with address <subnet>.i on the bridge; returns the address."""
        if not 1 <= i < ROOT_HOST:
            raise ValueError(f"host number {i} outside 1..{ROOT_HOST - 1}")
        ns = f"{self.prefix}-h{i}"
        _ip("netns", "add", ns)
        self.namespaces.append(ns)
        _ip("-n", self.switch, "link", "add", f"p{i}", "type", "veth", "peer", "name", "eth0", "netns", ns)
        _ip("-n", self.switch, "link", "set", f"p{i}", "master", "br0", "up")
        _ip("-n", ns, "addr", "add", f"{self.subnet}.{i}/24", "dev", "eth0")
        _ip("-n", ns, "link", "set", "eth0", "up")
        _ip("-n", ns, "link", "set", "lo", "up")
        self.hosts[i] = ns
        return self.address(i)

    def attach_root(self) -> str:
        """Put this (root) namespace on the bridge at <subnet>.254, e.g. for a simulator that must
        reach every host; returns that address. The cable is removed by cleanup()."""
        name = f"cd{os.getpid() % 100000}r{id(self) % 1000}"[:15]
        _ip("link", "add", name, "type", "veth", "peer", "name", "proot", "netns", self.switch)
        self.root_link = name
        _ip("-n", self.switch, "link", "set", "proot", "master", "br0", "up")
        _ip("addr", "add", f"{self.subnet}.{ROOT_HOST}/24", "dev", name)
        _ip("link", "set", name, "up")
        return self.address(ROOT_HOST)

    def address(self, i: int) -> str:
        return f"{self.subnet}.{i}"

    def range_spec(self, n: int) -> str:
        return f"{self.subnet}.1-{self.subnet}.{n}"

    def command(self, i: int, argv: list[str]) -> list[str]:
        """argv run inside host i's namespace (`ip netns exec` execs it: the pid is the program's)."""
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
        """Remove every namespace and cable this lab made (idempotent)."""
        if self.root_link is not None:
            _ip("link", "del", self.root_link, check=False)
            self.root_link = None
        for ns in reversed(self.namespaces):
            _ip("netns", "del", ns, check=False)
        self.namespaces.clear()
        self.hosts.clear()


class LoopbackLab:
    """The same interface on loopback: host i is 127.<a>.<b>.i; no cables to cut."""

    mode = "loopback"

    def __init__(self, tag: str = "coopdt", subnet: str | None = None):
        pid = os.getpid()
        self.subnet = subnet or f"127.{100 + pid % 100}.{pid // 100 % 250 + 1}"
        self.hosts: dict[int, str] = {}

    def add_host(self, i: int) -> str:
        self.hosts[i] = self.address(i)
        return self.hosts[i]

    def attach_root(self) -> str:
        return "127.0.0.1"

    def address(self, i: int) -> str:
        return f"{self.subnet}.{i}"

    def range_spec(self, n: int) -> str:
        return f"{self.subnet}.1-{self.subnet}.{n}"

    def command(self, i: int, argv: list[str]) -> list[str]:
        return argv

    def link(self, i: int, up: bool) -> None:
        raise RuntimeError("cutting a link needs network namespaces (root and iproute2)")

    def cleanup(self) -> None:
        self.hosts.clear()

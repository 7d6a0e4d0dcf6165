"""A virtual radio network for swarm tests and the demo: one Linux network namespace per drone on a
bridge (veth cables that can be unplugged and shaped), or loopback addresses when namespaces are
unavailable (not root, no iproute2). Only addresses this module creates are ever used.

    lab = NetnsLab("coopd-demo", "10.214.1"); addr = lab.add_host(1); lab.attach_root()
    subprocess.Popen(lab.command(1, ["coopd", ...])); lab.link(1, up=False); lab.cleanup()

Each host can also get a wired point-to-point cable to the root namespace (`add_fc_link`): a
drone's flight controller is wired to it, so its MAVLink must survive a radio cut and vice versa.

Namespace and root-side cable names carry the creating process id, so what a process killed -9
left behind is found and removed by `remove_stale()`.
"""

import os
import re
import shutil
import subprocess

ROOT_HOST = 254
"""Host number of the root namespace's own address on the bridge (the simulator's side)."""
FC_LINK_PREFIX = "cfc"
"""Root-side FC cable names: cfc<pid><lab letter><host> (at most 14 characters)."""
MAX_FC_HOSTS = 63
"""FC cables are /30s inside one /24: host i uses .4i+1 (root side) and .4i+2 (drone side)."""


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
    """Delete namespaces named <tag>-<pid>-... and root-side FC cables cfc<pid>... whose creating
    process is gone; returns their names."""
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
    return removed + remove_stale_fc_links()


def remove_stale_fc_links() -> list[str]:
    """Delete root-side FC cables whose creating process is gone (deleting a namespace already
    takes its veth pair along; this catches a cable whose namespace was removed some other way)."""
    try:
        links = _ip("-o", "link", "show", check=False).stdout
    except (OSError, subprocess.SubprocessError):
        return []
    removed = []
    for line in links.splitlines():
        parts = line.split(":")
        if len(parts) < 2:
            continue
        name = parts[1].strip().split("@")[0]
        m = re.fullmatch(rf"{FC_LINK_PREFIX}(\d+)[a-z]\d+", name)
        if m and not os.path.exists(f"/proc/{m.group(1)}"):
            _ip("link", "del", name, check=False)
            removed.append(name)
    return removed


class NetnsLab:
    """Namespaces <tag>-<pid>-<n>-{sw,h1,h2,...}: hosts on one bridge in the switch namespace,
    host i at <subnet>.i on its eth0, optionally wired to the root namespace by an FC cable
    (<fc_subnet>.4i+1 root side, .4i+2 on the host's fc0); removed by cleanup()."""

    mode = "netns"
    _serial = 0

    def __init__(self, tag: str = "coopdt", subnet: str = "10.213.1", fc_subnet: str = "10.215.1"):
        self.subnet = subnet
        self.fc_subnet = fc_subnet
        self.prefix = f"{tag}-{os.getpid()}-{id(self) % 100000}"
        NetnsLab._serial += 1
        self.letter = "abcdefghijklmnopqrstuvwxyz"[NetnsLab._serial % 26]
        self.switch = f"{self.prefix}-sw"
        self.namespaces: list[str] = []
        self.hosts: dict[int, str] = {}
        self.root_link: str | None = None
        self.fc_links: dict[int, str] = {}
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

    def add_fc_link(self, i: int) -> tuple[str, str]:
        """Wire host i to the root namespace point-to-point (its flight controller's cable, apart
        from the radio bridge); returns (root-side address, host-side address)."""
        if not 1 <= i <= MAX_FC_HOSTS:
            raise ValueError(f"FC cables exist for hosts 1..{MAX_FC_HOSTS}, not {i}")
        name = f"{FC_LINK_PREFIX}{os.getpid()}{self.letter}{i}"
        _ip("link", "add", name, "type", "veth", "peer", "name", "fc0", "netns", self.hosts[i])
        self.fc_links[i] = name
        root_addr, host_addr = self.fc_addresses(i)
        _ip("addr", "add", f"{root_addr}/30", "dev", name)
        _ip("link", "set", name, "up")
        _ip("-n", self.hosts[i], "addr", "add", f"{host_addr}/30", "dev", "fc0")
        _ip("-n", self.hosts[i], "link", "set", "fc0", "up")
        return root_addr, host_addr

    def fc_addresses(self, i: int) -> tuple[str, str]:
        """(root side, host side) addresses of host i's FC cable."""
        return f"{self.fc_subnet}.{4 * i + 1}", f"{self.fc_subnet}.{4 * i + 2}"

    def address(self, i: int) -> str:
        return f"{self.subnet}.{i}"

    def range_spec(self, n: int) -> str:
        return f"{self.subnet}.1-{self.subnet}.{n}"

    def command(self, i: int, argv: list[str]) -> list[str]:
        """argv run inside host i's namespace (`ip netns exec` execs it: the pid is the program's)."""
        return ["ip", "netns", "exec", self.hosts[i], *argv]

    def link(self, i: int, up: bool) -> None:
        """Cut or restore host i's radio (its port on the switch)."""
        _ip("-n", self.switch, "link", "set", f"p{i}", "up" if up else "down")

    def fc_link(self, i: int, up: bool) -> None:
        """Cut or restore host i's FC cable (its end inside the host, like a loose connector)."""
        _ip("-n", self.hosts[i], "link", "set", "fc0", "up" if up else "down")

    def shape(self, i: int, rate: str, burst: str = "32kb", latency: str = "50ms") -> None:
        """tc tbf on host i's egress (eth0) and on its switch port (traffic towards host i)."""
        for ns, dev in ((self.hosts[i], "eth0"), (self.switch, f"p{i}")):
            subprocess.run(["ip", "netns", "exec", ns, "tc", "qdisc", "replace", "dev", dev, "root", "tbf",
                            "rate", rate, "burst", burst, "latency", latency],
                           check=True, capture_output=True, timeout=10)

    def unshape(self, i: int) -> None:
        """Remove shape()'s limits from host i's links (no error if there were none)."""
        for ns, dev in ((self.hosts[i], "eth0"), (self.switch, f"p{i}")):
            subprocess.run(["ip", "netns", "exec", ns, "tc", "qdisc", "del", "dev", dev, "root"],
                           capture_output=True, timeout=10)

    def cleanup(self) -> None:
        """Remove every namespace and cable this lab made (idempotent)."""
        if self.root_link is not None:
            _ip("link", "del", self.root_link, check=False)
            self.root_link = None
        for name in self.fc_links.values():
            _ip("link", "del", name, check=False)
        self.fc_links.clear()
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

    def add_fc_link(self, i: int) -> tuple[str, str]:
        raise RuntimeError("a separate FC cable needs network namespaces (root and iproute2)")

    def link(self, i: int, up: bool) -> None:
        raise RuntimeError("cutting a link needs network namespaces (root and iproute2)")

    def fc_link(self, i: int, up: bool) -> None:
        raise RuntimeError("cutting a link needs network namespaces (root and iproute2)")

    def cleanup(self) -> None:
        self.hosts.clear()

"""Maps across hops over Zenoh, on hosts that reach only their neighbours: four network namespaces
in a line A-B-C-D, joined by three veth cables (no forwarding, no routes beyond each cable). Over
Zenoh with every drone a router, A's map reaches D, and a late D fetches every latest map by query;
over MTP without relay it does not; a cable
cut stops a new version and restoring it delivers it; on cables shaped to 2 Mbit/s the map takes
about the time its bytes need per hop."""

import os
import subprocess
import time

import pytest
from netns_support import Node, netns_unavailable_reason
from sharing_support import wait_until

from tests.proof import skip_proof

pytest.importorskip("zenoh")
pytestmark = pytest.mark.slow
PORT = 7400
ZENOH_PORT = 7447
HOSTS = 4


def _ip(*args: str) -> None:
    subprocess.run(["ip", *args], check=True, capture_output=True, timeout=10)


class LineLab:
    """Namespaces h1..hN, cable i joins h(i) (10.77.i.1) and h(i+1) (10.77.i.2); removed by cleanup()."""

    mode = "netns"

    def __init__(self, hosts: int):
        tag = f"cz{os.getpid() % 100000}"
        self.names = [f"{tag}-h{i}" for i in range(1, hosts + 1)]
        self.cables = []
        self.nodes: list[Node] = []
        for n in self.names:
            _ip("netns", "add", n)
            _ip("-n", n, "link", "set", "lo", "up")
        for i in range(1, hosts):
            left, right = f"{tag}c{i}a", f"{tag}c{i}b"
            _ip("link", "add", left, "netns", self.names[i - 1], "type", "veth", "peer", "name", right,
                "netns", self.names[i])
            for ns, dev, host in ((self.names[i - 1], left, 1), (self.names[i], right, 2)):
                _ip("-n", ns, "addr", "add", f"10.77.{i}.{host}/30", "dev", dev)
                _ip("-n", ns, "link", "set", dev, "up")
            self.cables.append((self.names[i - 1], left, self.names[i], right))

    def address(self, i: int) -> str:
        """Host i's address on the cable to its left neighbour (host 1: on the cable to host 2)."""
        return "10.77.1.1" if i == 1 else f"10.77.{i - 1}.2"

    def command(self, i: int, argv: list[str]) -> list[str]:
        return ["ip", "netns", "exec", self.names[i - 1], *argv]

    def cable(self, i: int, up: bool) -> None:
        """Cut or restore cable i (between host i and host i+1) at both ends."""
        left_ns, left, right_ns, right = self.cables[i - 1]
        for ns, dev in ((left_ns, left), (right_ns, right)):
            _ip("-n", ns, "link", "set", dev, "up" if up else "down")

    def shape(self, rate: str) -> None:
        for left_ns, left, right_ns, right in self.cables:
            for ns, dev in ((left_ns, left), (right_ns, right)):
                subprocess.run(["ip", "netns", "exec", ns, "tc", "qdisc", "add", "dev", dev, "root", "tbf",
                                "rate", rate, "burst", "32kbit", "latency", "400ms"], check=True, timeout=10)

    def cleanup(self) -> None:
        for n in self.nodes:
            n.kill()
            n.log_path.unlink(missing_ok=True)
        for n in self.names:
            subprocess.run(["ip", "netns", "del", n], capture_output=True, timeout=10)


@pytest.fixture
def line():
    reason = netns_unavailable_reason()
    if reason:
        skip_proof(f"the multi-hop Zenoh proof needs network namespaces: {reason}")
    lab = LineLab(HOSTS)
    try:
        yield lab
    finally:
        lab.cleanup()


def zenoh_node(lab: LineLab, i: int, *extra: str) -> Node:
    """Host i's sharing node: Zenoh only, a router, connected to its left neighbour's listener."""
    args = ["--no-mtp", "--zenoh-mode", "router", "--zenoh-listen", f"tcp/0.0.0.0:{ZENOH_PORT}", *extra]
    if i > 1:
        args += ["--zenoh-connect", f"tcp/10.77.{i - 1}.1:{ZENOH_PORT}"]
    node = Node(lab, i, i, PORT, "127.0.0.1", *args)
    lab.nodes.append(node)
    return node


def version_at(node: Node, vid: int) -> int | None:
    got = node.received().get(vid)
    return None if got is None else got[0]


def test_a_map_crosses_three_hops_over_zenoh_and_not_over_mtp(line):
    a, b, c = (zenoh_node(line, i) for i in range(1, HOSTS))
    a.publish(1, 20_000)
    c.publish(1, 20_000)
    assert wait_until(lambda: [version_at(n, 1) for n in (b, c)] == [1, 1] and version_at(a, 3) == 1, 30)
    # D joins late, three hops from A: nothing is published again, it fetches every latest map by query
    d = zenoh_node(line, HOSTS)
    assert wait_until(lambda: version_at(d, 1) == 1 and version_at(d, 3) == 1, 30), d.status()
    assert d.status()["zenoh"]["fetched"] >= 2
    d.publish(1, 20_000)
    assert wait_until(lambda: version_at(a, 4) == 1, 30), a.status()
    # a cable cut: a new version stops short of it; restored, it gets through
    line.cable(2, up=False)
    a.publish(2, 20_000)
    assert wait_until(lambda: version_at(b, 1) == 2, 30)
    time.sleep(2.0)
    assert version_at(d, 1) == 1
    t_restored = time.monotonic()
    line.cable(2, up=True)
    assert wait_until(lambda: version_at(d, 1) == 2, 60), d.status()
    print(f"after the cable came back: version 2 at D in {time.monotonic() - t_restored:.1f} s")
    for n in (a, b, c, d):
        n.stop()
    line.nodes.clear()
    # the same line over MTP, relay off, each host scanning its neighbours: A's map stays one hop away
    mtp = []
    for i in range(1, HOSTS + 1):
        neighbours = ",".join(line.address(j) for j in (i - 1, i + 1) if 1 <= j <= HOSTS)
        node = Node(line, i, i, PORT, neighbours.split(",")[0], "--real")
        line.nodes.append(node)
        mtp.append(node)
    mtp[0].publish(1, 20_000)
    assert wait_until(lambda: version_at(mtp[1], 1) == 1, 30)
    time.sleep(3.0)
    assert version_at(mtp[3], 1) is None and version_at(mtp[2], 1) is None


def test_shaped_cables_carry_the_map_at_their_rate(line):
    line.shape("2mbit")
    nodes = [zenoh_node(line, i, "--real") for i in range(1, HOSTS + 1)]
    nodes[0].publish(1, 1000)  # the routers' sessions and routes up: a first small map crosses
    assert wait_until(lambda: version_at(nodes[3], 1) == 1, 60), nodes[3].status()
    before = nodes[3].status()["zenoh"]["bytes_in"]
    t0 = time.monotonic()
    nodes[0].publish(2, 400_000)
    assert wait_until(lambda: version_at(nodes[3], 1) == 2, 60), nodes[3].status()
    seconds = time.monotonic() - t0
    size = nodes[3].status()["zenoh"]["bytes_in"] - before  # the envelope as it arrived
    per_hop = size * 8 / 2e6
    print(f"{size} bytes across 3 cables at 2 Mbit/s: {seconds:.2f} s (one cable takes {per_hop:.2f} s)")
    assert seconds >= per_hop * 0.9  # the shaping holds: not faster than one cable allows

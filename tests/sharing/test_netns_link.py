"""Link-level tests that need network namespaces: a cable pulled mid-transfer, and a tc tbf shaped
link whose transfer time must match size / bandwidth with little protocol overhead."""

import hashlib
import shutil
import time

import pytest
import sharing_testmsg as tm
from netns_support import NetnsLab, Node, netns_unavailable_reason
from sharing_node import payload
from sharing_support import wait_until

REASON = netns_unavailable_reason() or (None if shutil.which("tc") else "tc not found")
pytestmark = pytest.mark.skipif(REASON is not None, reason=f"needs network namespaces and tc: {REASON} "
                                "(the kill-mid-transfer case runs on loopback in test_netns_swarm)")
PORT = 7400


@pytest.fixture
def lab():
    the_lab = NetnsLab()
    the_lab.nodes = []
    try:
        yield the_lab
    finally:
        for n in the_lab.nodes:
            n.kill()
            n.log_path.unlink(missing_ok=True)
        the_lab.cleanup()


def start(lab, i, vid, *extra) -> Node:
    node = Node(lab, i, vid, PORT, lab.range_spec(3), *extra)
    lab.nodes.append(node)
    return node


def received(node: Node, vid: int):
    return node.received().get(vid)


def digest(vid, version, size):
    return hashlib.sha256(tm.make(vid, version, payload(vid, version, size))).hexdigest()


def test_cable_pulled_mid_transfer_then_restored(lab):
    for i in (1, 2, 3):
        lab.add_host(i)
    a, b = start(lab, 1, 21), start(lab, 2, 22)
    c = start(lab, 3, 23, "--rate", "2000000")
    for n in (a, b, c):
        n.publish(1, 20_000)
    assert wait_until(lambda: received(a, 23) is not None and received(b, 23) is not None, 20)
    c.publish(2, 6_000_000)  # 3 s per peer at 2 MB/s
    time.sleep(1.0)
    lab.link(3, up=False)
    time.sleep(3.0)  # receivers time out the silent transfer and drop it whole
    for n in (a, b):
        assert received(n, 23)[0] == 1, n.received()
        st = {p["vehicle_id"]: p for p in n.status()["peers"]}
        assert sum(st[23]["failures"].values()) >= 1, st[23]
    a.publish(2, 20_000)
    assert wait_until(lambda: received(b, 21)[0] == 2, 10)
    lab.link(3, up=True)
    for n in (a, b):
        assert wait_until(lambda n=n: (received(n, 23) or [0])[0] == 2, 40), n.received()
        assert received(n, 23)[2] == digest(23, 2, 6_000_000)
    assert wait_until(lambda: received(c, 21)[0] == 2, 20)


def test_tbf_shaped_link_transfer_time_matches_bandwidth(lab):
    rate_bit = 20e6
    for i in (1, 2):
        lab.add_host(i)
    lab.shape(1, "20mbit")
    a, b = start(lab, 1, 31), start(lab, 2, 32)
    size = 5_000_000
    a.publish(1, size)
    assert wait_until(lambda: received(b, 31) is not None, 30)
    peer = {p["vehicle_id"]: p for p in a.status()["peers"]}[32]
    nbytes = peer["bytes_sent"]
    measured = peer["last_transfer_s"]
    ideal = nbytes * 8 / rate_bit
    ratio = measured / ideal
    print(f"tbf 20mbit: {nbytes} bytes in {measured:.3f} s, ideal {ideal:.3f} s, ratio {ratio:.3f}")
    # The link, not the protocol, sets the pace: never faster than the shaped rate, and the
    # overhead stays small (1.02-1.09 on an idle machine; the bound leaves room for a loaded CI
    # host, where a starved receiver thread adds latency). scripts/bench share has the figures.
    assert 1.0 <= ratio < 1.35, ratio

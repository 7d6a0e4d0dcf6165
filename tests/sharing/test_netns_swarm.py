"""Multi-host sharing: three endpoints on their own addresses (network namespaces on a bridge, or
loopback addresses when namespaces are unavailable) find each other by range scan, exchange maps,
survive a host vanishing mid-transfer without publishing anything partial, and resynchronise."""

import hashlib
import time

import pytest
import sharing_testmsg as tm
from netns_support import LoopbackLab, NetnsLab, Node, netns_unavailable_reason
from sharing_node import payload, real_map
from sharing_support import free_port, wait_until

from tests.proof import skip_proof

NETNS_REASON = netns_unavailable_reason()


def digest(vid: int, version: int, size: int) -> str:
    return hashlib.sha256(tm.make(vid, version, payload(vid, version, size))).hexdigest()


@pytest.fixture(params=["netns", "loopback"])
def lab(request):
    if request.param == "netns" and NETNS_REASON:
        skip_proof(f"network namespaces unavailable ({NETNS_REASON}); the loopback variant runs instead")
    if request.param == "loopback" and not NETNS_REASON:
        pytest.skip("network namespaces available: the netns variant of this test ran instead")
    the_lab = NetnsLab() if request.param == "netns" else LoopbackLab()
    nodes: list[Node] = []
    the_lab.nodes = nodes
    print(f"multi-host mode: {the_lab.mode}")
    request.node.user_properties.append(("multi_host_mode", the_lab.mode))
    try:
        yield the_lab
    finally:
        for n in nodes:
            n.kill()
        for n in nodes:
            n.log_path.unlink(missing_ok=True)
        the_lab.cleanup()


def start(lab, i: int, vid: int, port: int, *extra: str) -> Node:
    node = Node(lab, i, vid, port, lab.range_spec(4), *extra)
    lab.nodes.append(node)
    return node


def holds(node: Node, expected: dict) -> bool:
    got = node.received()
    return all(got.get(v, [None, None, None])[0] == ver and got[v][2] == d
               for v, (ver, d) in expected.items())


def failure_counts(node: Node, vid: int) -> dict:
    for p in node.status()["peers"]:
        if p["vehicle_id"] == vid:
            return p["failures"]
    return {}


def test_three_hosts_exchange_survive_a_kill_and_resync(lab):
    port = 7400 if lab.mode == "netns" else free_port(lab.address(1))
    for i in (1, 2, 3):
        lab.add_host(i)
    small = 50_000
    a, b = start(lab, 1, 11, port), start(lab, 2, 12, port)
    c = start(lab, 3, 13, port, "--rate", "2000000")  # 2 MB/s: its big map takes seconds to send
    for n in (a, b, c):
        n.publish(1, small)
    v1 = {n.vid: (1, digest(n.vid, 1, small)) for n in (a, b, c)}
    for n in (a, b, c):
        others = {v: x for v, x in v1.items() if v != n.vid}
        assert wait_until(lambda n=n, others=others: holds(n, others), 20), (lab.mode, n.vid, n.received())

    # C starts sending a big map (about 4 s per peer) and dies after 1 s
    c.publish(2, 8_000_000)
    time.sleep(1.0)
    c.kill()
    time.sleep(0.5)
    for n in (a, b):
        assert holds(n, {13: v1[13]}), n.received()  # still the complete v1: nothing partial
    assert wait_until(lambda: failure_counts(a, 13) or failure_counts(b, 13), 5)
    # the others carry on
    a.publish(2, small)
    assert wait_until(lambda: holds(b, {11: (2, digest(11, 2, small))}), 10)

    # C comes back (new process, same vehicle, same address): everyone resynchronises
    c2 = start(lab, 3, 13, port)
    c2.publish(3, small)
    assert wait_until(lambda: holds(a, {13: (3, digest(13, 3, small))}) and
                      holds(b, {13: (3, digest(13, 3, small))}), 20)
    assert wait_until(lambda: holds(c2, {11: (2, digest(11, 2, small)), 12: v1[12]}), 20), c2.received()
    peers = {p["vehicle_id"]: p for p in a.status()["peers"]}
    assert set(peers) == {12, 13} and peers[13]["address"] == lab.address(3)


def test_real_map_messages_cross_processes_and_hosts(lab):
    """Real wire messages (encode_map) between three processes: inspected, fully decoded by each
    receiver before it acknowledges, stored byte-identical."""
    port = 7400 if lab.mode == "netns" else free_port(lab.address(1))
    for i in (1, 2, 3):
        lab.add_host(i)
    nodes = [start(lab, i, 40 + i, port, "--real") for i in (1, 2, 3)]
    for n in nodes:
        n.publish(1, 200_000)
    for n in nodes:
        want = {m.vid: (1, hashlib.sha256(real_map(m.vid, 1, 200_000)).hexdigest())
                for m in nodes if m is not n}
        assert wait_until(lambda n=n, want=want: holds(n, want), 20), (lab.mode, n.vid, n.received())

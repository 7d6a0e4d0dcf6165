"""Relay (multi-hop): maps cross a line of drones that are not all in range of each other, never
loop back, and are not resent to a peer that already holds them."""

import time

import pytest
import sharing_testmsg as tm
from sharing_support import free_port, service, wait_until


@pytest.fixture
def net():
    started = []

    def make(vid, host, port, peers, relay=True):
        svc = service(vid, host, port, peers=peers, peer_ports=[port], relay=relay).start()
        started.append(svc)
        return svc

    yield make
    for svc in started:
        svc.stop()


def total_sent(*svcs) -> int:
    """Transfers made, accepted or answered 'stale'."""
    return sum(p["maps_sent"] + p["redundant_sent"] for s in svcs for p in s.stats()["peers"])


def test_line_topology_relays_both_ways_without_loops(net):
    port = free_port("127.0.0.61")
    # A and C only know B; B knows both: A - B - C
    a = net(1, "127.0.0.61", port, ["127.0.0.62"])
    b = net(2, "127.0.0.62", port, ["127.0.0.61", "127.0.0.63"])
    c = net(3, "127.0.0.63", port, ["127.0.0.62"])
    for s in (a, b, c):
        s.publish(tm.make(s.vehicle_id, 1, bytes([s.vehicle_id]) * 500), 1)
    assert wait_until(lambda: c.received.version(1) == 1 and a.received.version(3) == 1, 10)
    assert c.received.get(1).via == 2 and a.received.get(3).via == 2
    time.sleep(1.0)
    settled = total_sent(a, b, c)
    # exactly one transfer per map per link direction that needs it: A->B, B->C (A's map),
    # C->B, B->A (C's map), B->A, B->C (B's map); B never echoes a map to where it came from
    assert settled == 6, settled
    time.sleep(1.0)
    assert total_sent(a, b, c) == settled  # nothing circulates
    # a new version travels the line once
    a.publish(tm.make(1, 2, b"new"), 2)
    assert wait_until(lambda: c.received.version(1) == 2, 10)
    time.sleep(0.6)
    assert total_sent(a, b, c) == settled + 2


def test_full_mesh_with_relay_converges_and_goes_quiet(net):
    port = free_port("127.0.0.71")
    spec = ["127.0.0.71-127.0.0.73"]
    svcs = [net(v, f"127.0.0.7{v}", port, spec) for v in (1, 2, 3)]
    for s in svcs:
        s.publish(tm.make(s.vehicle_id, 1, b"m" * 300), 1)
    assert wait_until(lambda: all(len(s.received.all()) == 2 for s in svcs), 10)
    time.sleep(2.0)  # past relay_delay
    settled = total_sent(*svcs)
    # 6 direct sends; relays wait relay_delay, by then every peer has every map from its origin
    assert settled == 6, settled
    print("full mesh transfers until quiet:", settled)
    time.sleep(1.0)
    assert total_sent(*svcs) == settled


def test_relay_off_keeps_maps_one_hop(net):
    port = free_port("127.0.0.81")
    a = net(1, "127.0.0.81", port, ["127.0.0.82"], relay=False)
    b = net(2, "127.0.0.82", port, ["127.0.0.81", "127.0.0.83"], relay=False)
    c = net(3, "127.0.0.83", port, ["127.0.0.82"], relay=False)
    for s in (a, b, c):
        s.publish(tm.make(s.vehicle_id, 1, b"x"), 1)
    assert wait_until(lambda: b.received.version(1) == 1 and b.received.version(3) == 1, 10)
    time.sleep(0.8)
    assert c.received.version(1) == -1 and a.received.version(3) == -1

"""Discovery: target expansion, non-blocking probes, self-detection, vehicle-id identity, grace period."""

import ipaddress
import socket
import time

import pytest
import sharing_testmsg as tm
from sharing_support import free_port, service, wait_until

from coopd.net import host_port
from coopd.sharing import discovery
from tests.loopback import has_ipv6_loopback


def test_parse_ranges_lists_and_ports():
    t = discovery.parse_targets(["10.42.0.1-10.42.0.3", "10.42.0.9", "h:7401", "10.42.0.2-3"], [7400, 7402])
    assert t[:6] == [("10.42.0.1", 7400), ("10.42.0.1", 7402), ("10.42.0.2", 7400), ("10.42.0.2", 7402),
                     ("10.42.0.3", 7400), ("10.42.0.3", 7402)]
    assert ("10.42.0.9", 7402) in t and ("h", 7401) in t and ("h", 7400) not in t
    assert len(t) == len(set(t))


@pytest.mark.parametrize("bad", ["10.0.0.5-10.0.0.1", "10.0.0.0-10.1.0.0", "x-y", "h:0", "h:70000"])
def test_bad_specs_are_refused(bad):
    with pytest.raises(ValueError):
        discovery.parse_targets([bad], [7400])


def test_probe_returns_only_listening_targets_within_timeout():
    port = free_port("127.0.0.31")
    with socket.socket() as ls:
        ls.bind(("127.0.0.32", port))
        ls.listen()
        targets = discovery.parse_targets(["127.0.0.31-127.0.0.34"], [port])
        t0 = time.monotonic()
        found = discovery.probe(targets, 0.5)
        took = time.monotonic() - t0
    try:
        assert [t for t, _ in found] == [("127.0.0.32", port)]
        assert took < 2.0  # all probed at once: one 0.5 s timeout, not four
    finally:
        for _, s in found:
            s.close()


def test_self_is_skipped_and_peer_found_by_range():
    port = free_port("127.0.0.41")
    a = service(1, "127.0.0.41", port, peers=["127.0.0.41-127.0.0.43"], peer_ports=[port]).start()
    b = service(2, "127.0.0.42", port).start()
    try:
        a.publish(tm.make(1, 1, b"x"), 1)
        assert wait_until(lambda: b.received.version(1) == 1, 5)
        assert wait_until(lambda: ("127.0.0.41", port) in a._self_targets, 3)
        peers = a.stats()["peers"]
        assert [p["vehicle_id"] for p in peers] == [2] and peers[0]["connected"]
    finally:
        a.stop()
        b.stop()


def test_peer_is_its_vehicle_id_across_addresses_and_dropped_after_grace():
    port = free_port("127.0.0.51")
    a = service(1, "127.0.0.51", port, peers=["127.0.0.52-127.0.0.53"], peer_ports=[port],
                grace_period=0.8).start()
    try:
        a.publish(tm.make(1, 1, b"x"), 1)
        b = service(2, "127.0.0.52", port).start()
        assert wait_until(lambda: b.received.version(1) == 1, 5)
        b.stop()
        # vehicle 2 comes back on another address: same peer entry, it lost its state -> resent
        b2 = service(2, "127.0.0.53", port).start()
        try:
            assert wait_until(lambda: b2.received.version(1) == 1, 6)
            peers = a.stats()["peers"]
            assert len(peers) == 1 and peers[0]["vehicle_id"] == 2 and peers[0]["address"] == "127.0.0.53"
        finally:
            b2.stop()
        assert wait_until(lambda: a.stats()["peers"] == [], 5)
    finally:
        a.stop()


def test_transport_settings_are_validated():
    from coopd.sharing.transport import TransportSettings

    for bad in ({"block_size": 10}, {"min_rate": 0}, {"read_timeout": -1}, {"max_connections": 0},
                {"swarm_key": b"short"}, {"max_send_rate": -1}):
        with pytest.raises(ValueError):
            TransportSettings(**bad)


def test_failed_handshakes_back_off_instead_of_retrying_every_scan():
    port = free_port("127.0.0.101")
    a = service(1, "127.0.0.101", port, peers=["127.0.0.102"], peer_ports=[port], scan_period=0.1).start()
    b = service(2, "127.0.0.102", port, swarm_key=b"k" * 32).start()  # a has no key: every hello fails
    try:
        time.sleep(2.0)
        auth = failures_of(a).get("auth", 0)
        # without backoff: ~20 attempts in 2 s at a 0.1 s scan period; with it: 0.1+0.2+0.4+0.8 s
        assert 2 <= auth <= 6, auth
    finally:
        a.stop()
        b.stop()


def test_a_vehicle_reachable_at_two_addresses_gets_one_sender():
    port = free_port("127.0.0.111")
    # two names for one server: the dotted address and its 32-bit integer form (as inet_aton reads it)
    alias = str(int(ipaddress.IPv4Address("127.0.0.112")))
    a = service(1, "127.0.0.111", port, peers=["127.0.0.112", alias], peer_ports=[port]).start()
    b = service(2, "127.0.0.112", port).start()
    try:
        a.publish(tm.make(1, 1, b"x"), 1)
        assert wait_until(lambda: b.received.version(1) == 1, 5)
        time.sleep(1.0)
        assert len(a._senders) == 1
        assert b.stats()["peers"][0]["maps_received"] == 1
        # one connection per name, then the alias is left alone (not re-tried every 0.2 s scan)
        assert b.stats()["connections_accepted"] == 2, b.stats()["connections_accepted"]
    finally:
        a.stop()
        b.stop()


def failures_of(svc) -> dict:
    out: dict = {}
    snap = svc.peers.snapshot()
    for p in snap["peers"]:
        for k, v in p["failures"].items():
            out[k] = out.get(k, 0) + v
    for counts in snap["unidentified_failures"].values():
        for k, v in counts.items():
            out[k] = out.get(k, 0) + v
    return out


def test_ipv6_peer_specs():
    t = discovery.parse_targets(["fd00::7", "[fd00::8]:7401", "[::1]", "FD00:0::9"], [7400])
    assert t == [("fd00::7", 7400), ("fd00::8", 7401), ("::1", 7400), ("fd00::9", 7400)]


@pytest.mark.parametrize("bad", ["[fd00::7", "[zz::1]:7400", "[::1]7400", "fd00::zz", "[::1]:0", "fd00::1-5"])
def test_bad_ipv6_specs_are_refused_by_the_service_and_the_config_check(bad):
    from coopd.daemon.config import ConfigError, parse_config

    with pytest.raises(ValueError) as refused:
        discovery.parse_targets([bad], [7400])
    with pytest.raises(ConfigError) as check:
        parse_config(f"[sharing]\npeers = [{bad!r}]")
    assert check.value.key == "sharing.peers" and str(refused.value) in str(check.value)


def test_ipv4_peers_of_a_dual_stack_listener_are_known_by_their_ipv4_address():
    assert discovery.peer_address("::ffff:10.42.0.7") == "10.42.0.7"
    assert discovery.peer_address("fd00::7") == "fd00::7" and discovery.peer_address("10.0.0.1") == "10.0.0.1"
    assert host_port("fd00::7", 7400) == "[fd00::7]:7400"


@pytest.mark.skipif(not has_ipv6_loopback(), reason="no IPv6 loopback (::1) on this machine")
def test_maps_are_shared_over_ipv6():
    """Map server on ::1, the peer found by its bracketed address, the map delivered both ways."""
    port_a, port_b = free_port("::1"), free_port("::1")
    a = service(1, "::1", port_a, peers=[f"[::1]:{port_b}"]).start()
    b = service(2, "::1", port_b, peers=[f"[::1]:{port_a}"]).start()
    try:
        assert a.stats()["listen"] == f"[::1]:{port_a}"
        a.publish(tm.make(1, 1, b"x"), 1)
        b.publish(tm.make(2, 1, b"y"), 1)
        assert wait_until(lambda: b.received.version(1) == 1 and a.received.version(2) == 1, 5)
        peers = a.stats()["peers"]
        assert [(p["vehicle_id"], p["address"]) for p in peers] == [(2, "::1")]
    finally:
        a.stop()
        b.stop()

"""Merge results (wire type 2) shared between two SharingService instances on loopback: delivered
once per version, authenticated with the swarm key like maps, and refused when relayed or corrupt."""

import contextlib
import socket

import numpy as np
import pytest
from sharing_support import failures, settings, wait_until

from coopd.geometry import rigid, rotation_z
from coopd.sharing import mtp, wire
from coopd.sharing.service import SharingConfig, SharingService
from coopd.sharing.transport import PeerLink

KEY = b"swarm-key-for-results-0123456789"


@pytest.fixture
def ports() -> tuple[int, int, int]:
    """Three distinct loopback TCP ports the kernel just handed out (held open together while picked):
    this test's services listen on them and scan exactly them for peers."""
    with contextlib.ExitStack() as stack:
        socks = [stack.enter_context(socket.socket()) for _ in range(3)]
        for s in socks:
            s.bind(("127.0.0.1", 0))
        return tuple(s.getsockname()[1] for s in socks)


def _service(vid, port, ports, key=KEY, peers=()):
    cfg = SharingConfig(vehicle_id=vid, listen_host="127.0.0.1", port=port, peers=tuple(peers),
                        peer_ports=ports, scan_period=0.2, transport=settings(swarm_key=key))
    return SharingService(cfg)


def _result(vid, version, b=3):
    edge = wire.MergeEdge(vid, b, rigid(rotation_z(0.5), [2.0, 1.0, 0.0]), 0.98, 0.3, 4, 9, wire.EDGE_FULL)
    return wire.encode_merge_result(wire.MergeResultMessage(vid, version, 1.7e9, (edge,)))


@pytest.fixture
def started():
    out = []
    yield out
    for svc in out:
        svc.stop()


def test_results_reach_a_keyed_peer_once_per_version_and_a_wrong_key_gets_none(started, ports):
    a = _service(1, ports[0], ports, peers=["127.0.0.1"])  # senders run on the scanning side
    b = _service(2, ports[1], ports, peers=["127.0.0.1"])
    intruder = _service(3, ports[2], ports, key=b"another-swarm-key-0123456789abcd", peers=["127.0.0.1"])
    started += [a.start(), b.start(), intruder.start()]
    a.publish_result(_result(1, 1), 1)
    assert wait_until(lambda: b.results.version(1) == 1)
    got = b.results.all()[0]
    assert got.edges[0].b == 3 and np.allclose(got.edges[0].transform[:3, 3], [2.0, 1.0, 0.0])
    a.publish_result(_result(1, 2, b=4), 2)
    assert wait_until(lambda: b.results.version(1) == 2)
    assert [e.b for e in b.results.all()[0].edges] == [4]
    peer = next(p for p in a.stats()["peers"] if p["vehicle_id"] == 2)
    assert peer["results_sent"] == 2 and peer["maps_sent"] == 0 and peer["has_result_versions"] == {1: 2}
    assert a.stats()["published_result_version"] == 2 and b.stats()["received_results"] == {1: 2}
    with pytest.raises(ValueError, match="not newer"):
        a.publish_result(_result(1, 2), 2)
    assert wait_until(lambda: failures(a).get("auth", 0) >= 1 or failures(intruder).get("auth", 0) >= 1)
    assert intruder.results.all() == [] and a.results.all() == []  # nothing crossed the wrong key


def test_relayed_or_corrupt_results_are_refused_and_counted(started, ports):
    a = _service(1, ports[0], ports)
    started.append(a.start())
    link = PeerLink.connect("127.0.0.1", ports[0], settings(swarm_key=KEY), 5)
    try:
        assert link.send_map(_result(7, 1))[0] == mtp.ACK_REJECTED  # vehicle 7's result sent by 5
    except (OSError, ValueError):
        pass  # the server may close the connection right after its ack
    link.close()
    corrupt = bytearray(_result(5, 1))
    corrupt[-10] ^= 0xFF  # edge bytes changed: the CRC no longer matches
    link = PeerLink.connect("127.0.0.1", ports[0], settings(swarm_key=KEY), 5)
    try:
        assert link.send_map(bytes(corrupt))[0] == mtp.ACK_REJECTED
    except (OSError, ValueError):
        pass
    link.close()
    assert wait_until(lambda: failures(a).get("relayed_result") == 1 and failures(a).get("decode") == 1), \
        failures(a)
    assert a.results.all() == []
    link = PeerLink.connect("127.0.0.1", ports[0], settings(swarm_key=KEY), 5)
    assert link.send_map(_result(5, 1))[0] == mtp.ACK_OK
    assert link.send_map(_result(5, 1))[0] == mtp.ACK_STALE
    link.close()
    assert a.results.version(5) == 1

"""Store exhaustion and made-up vehicle ids: ids outside the swarm's range are refused at receive,
a store full of vehicles never heard from again makes room for a new drone, and an allow-list
keeps unknown ids out altogether."""

import socket

import pytest
import sharing_testmsg as tm
from sharing_support import failures, settings, wait_until
from test_transport_hostile import closed_by_server

from coopd.sharing import mtp
from coopd.sharing.transport import PeerLink


def link(svc, vid: int = 9) -> PeerLink:
    return PeerLink.connect(*svc.address, settings(), vid)


def test_made_up_vehicles_cannot_keep_a_new_drone_out(server):
    """One host sends maps for 254 made-up vehicle ids (every id but ours and the new drone's);
    then a genuinely new drone's map must be stored."""
    svc = server()
    svc.received.max_vehicles = 64
    attacker = link(svc, 9)
    try:
        fakes = [v for v in range(2, 256) if v != 200]
        for vid in fakes:
            assert attacker.send_map(tm.make(vid, 1, b"f" * 20))[0] == mtp.ACK_OK
    finally:
        attacker.close()
    assert len(svc.received.all()) == 64
    drone = link(svc, 200)
    try:
        assert drone.send_map(tm.make(200, 1, b"new drone"))[0] == mtp.ACK_OK
    finally:
        drone.close()
    held = {m.vehicle_id for m in svc.received.all()}
    assert 200 in held and len(held) == 64 and fakes[-64] not in held and fakes[-63] in held  # stalest went
    assert svc.stats()["evicted_maps"] == len(fakes) - 64 + 1
    assert failures(svc) == {}


@pytest.mark.parametrize("vid", [0, 256, -1, 2**31 - 1])
def test_vehicle_ids_outside_the_swarm_range_are_refused(server, vid):
    svc = server()
    sender = link(svc, 9)
    try:
        assert sender.send_map(tm.make(9, 1, b"ok"))[0] == mtp.ACK_OK
        assert sender.send_map(tm.make(vid & 0xFFFFFFFF, 1, b"x"))[0] == mtp.ACK_REJECTED
    finally:
        sender.close()
    assert wait_until(lambda: failures(svc) == {"vehicle_id": 1}, 3), failures(svc)
    assert [m.vehicle_id for m in svc.received.all()] == [9]
    with socket.create_connection(svc.address, timeout=2) as s:  # a hello claiming such an id
        s.sendall(mtp.hello_frame(mtp.Hello(256, vid, b"n" * 16, False)))
        s.settimeout(2)
        s.recv(256)  # the server's hello
        assert closed_by_server(s)
    assert wait_until(lambda: failures(svc) == {"vehicle_id": 2}, 3), failures(svc)


def test_an_allow_list_keeps_other_vehicle_ids_out(server):
    svc = server()
    svc.config = type(svc.config)(**{**svc.config.__dict__, "allowed_vehicles": frozenset({5, 9})})
    sender = link(svc, 9)
    try:
        assert sender.offer(6, 1) == mtp.ACK_STALE and sender.offer(5, 1) == mtp.ACK_OK  # not wanted
        assert sender.send_map(tm.make(5, 1, b"a"))[0] == mtp.ACK_OK
        assert sender.send_map(tm.make(6, 1, b"b"))[0] == mtp.ACK_REJECTED
    finally:
        sender.close()
    assert wait_until(lambda: failures(svc) == {"not_allowed": 1}, 3), failures(svc)
    assert [m.vehicle_id for m in svc.received.all()] == [5]

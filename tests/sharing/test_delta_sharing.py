"""Map deltas over MTP: two services on loopback exchange a growing map over many versions and end with
identical maps on fewer bytes; a peer that does not read deltas gets full maps; a delta whose base the
receiver does not hold, or a malformed one, is refused, counted, and changes nothing."""

import numpy as np
import pytest
from sharing_support import failures, growing_maps, settings, wait_until

from coopd.grid import OccupancyGrid
from coopd.sharing import delta, mtp, wire
from coopd.sharing.service import SharingConfig, SharingService, wire_inspect, wire_verifier
from coopd.sharing.transport import PeerLink
from coopd.sharing.wire import MapMeta

LIMITS = dict(max_bytes=4 << 20, max_cells=1 << 22)


def real_service(vid: int, peers=(), deltas: bool = True, **transport) -> SharingService:
    """A service of vehicle vid on 127.0.0.vid reading real map messages (wire format, full decode)."""
    host = f"127.0.0.{vid}"
    s = settings(**{**LIMITS, "block_size": 512, **transport})
    cfg = SharingConfig(vehicle_id=vid, listen_host=host, port=0, peers=tuple(peers), scan_period=0.2,
                        deltas=deltas, transport=s)
    return SharingService(cfg, inspect=wire_inspect, verify=wire_verifier(s.max_cells, s.max_bytes)).start()


def exchange(deltas: bool, maps) -> tuple[SharingService, SharingService]:
    """Vehicle 1 publishes every map, waiting each time until vehicle 2 holds it; both returned (running)."""
    b = real_service(2, deltas=deltas)
    a = real_service(1, peers=(f"127.0.0.2:{b.address[1]}",), deltas=deltas)
    for grid, v, message in maps:
        a.publish(message, v, grid)
        assert wait_until(lambda v=v: b.received.version(1) == v, 10), f"v{v} not received"
    return a, b


def peer_stats(svc: SharingService, vid: int) -> dict:
    return next(p for p in svc.stats()["peers"] if p["vehicle_id"] == vid)


def test_two_daemons_end_with_identical_maps_and_deltas_cost_fewer_bytes():
    maps = growing_maps(16)
    sent = {}
    for deltas in (True, False):
        a, b = exchange(deltas, maps)
        try:
            grid, meta = b.decode(1)
            last_grid, last_v, last_message = maps[-1]
            assert meta.version == last_v
            assert grid.shape == last_grid.shape and np.array_equal(grid.offset, last_grid.offset)
            assert np.array_equal(grid.cells, last_grid.cells)
            assert bytes(b.received.get(1).data) == last_message  # the full message, byte for byte
            assert wait_until(lambda a=a: peer_stats(a, 2)["maps_sent"] == len(maps), 5)  # last ack counted
            stats = peer_stats(a, 2)
            sent[deltas] = stats
            assert peer_stats(b, 1)["deltas_received"] == stats["deltas_sent"]
            assert not failures(a) and not failures(b)
        finally:
            a.stop()
            b.stop()
    assert sent[False]["deltas_sent"] == 0
    assert sent[True]["deltas_sent"] >= len(maps) - 2  # the first map travels in full
    assert sent[True]["delta_fallbacks"] == 0
    print(f"wire bytes sent: full maps {sent[False]['wire_bytes_sent']}, "
          f"deltas {sent[True]['wire_bytes_sent']}")
    assert sent[True]["bytes_sent"] * 3 < sent[False]["bytes_sent"]
    assert sent[True]["wire_bytes_sent"] * 2 < sent[False]["wire_bytes_sent"]


def test_a_peer_that_does_not_read_deltas_gets_full_maps():
    """An older coopd (its hello does not say it reads deltas) is sent full maps, and holds them right."""
    maps = growing_maps(5, seed=1)
    b = real_service(2, deltas=False)
    a = real_service(1, peers=(f"127.0.0.2:{b.address[1]}",), deltas=True)
    try:
        for grid, v, message in maps:
            a.publish(message, v, grid)
            assert wait_until(lambda v=v: b.received.version(1) == v, 10)
        assert peer_stats(a, 2)["deltas_sent"] == 0
        assert bytes(b.received.get(1).data) == maps[-1][2]
    finally:
        a.stop()
        b.stop()


def test_a_receiver_that_lost_the_base_gets_the_full_map():
    """When the receiver no longer holds the base the sender believes it holds (its map of the sender was
    evicted), the delta is refused with 'base not held' and the full map follows at once on the same
    connection; the next version goes as a delta again."""
    maps = growing_maps(4, seed=2)
    b = real_service(2)
    a = real_service(1, peers=(f"127.0.0.2:{b.address[1]}",))
    try:
        for grid, v, message in maps[:2]:
            a.publish(message, v, grid)
            assert wait_until(lambda v=v: b.received.version(1) == v, 10)
        with b.received._lock:  # the store forgot it (as an eviction does)
            b.received._maps.clear()
            b.received._bytes = 0
        grid, v, message = maps[2]
        a.publish(message, v, grid)
        assert wait_until(lambda: b.received.version(1) == v, 10)
        assert bytes(b.received.get(1).data) == message
        assert peer_stats(a, 2)["delta_fallbacks"] == 1
        assert failures(b) == {"delta_base": 1}
        grid, v, message = maps[3]
        a.publish(message, v, grid)
        assert wait_until(lambda: b.received.version(1) == v, 10)
        assert wait_until(lambda: peer_stats(a, 2)["deltas_sent"] == 2, 5)  # v2 and v4
        assert peer_stats(a, 2)["delta_fallbacks"] == 1
    finally:
        a.stop()
        b.stop()


# ------------------------------------------------------------------------------------ hostile deltas
def send(svc: SharingService, message: bytes, vid: int = 7) -> int:
    link = PeerLink.connect(*svc.address, settings(**LIMITS, block_size=512), vid, source="127.0.0.7")
    try:
        return link.send_map(message)[0]
    finally:
        link.close()


@pytest.fixture
def receiver():
    svc = real_service(2)
    yield svc
    svc.stop()


def held_versions(vid: int = 7):
    """Versions 1 and 2 of vehicle vid's map, and the delta from 1 to 2."""
    maps = growing_maps(2, seed=3)
    ledger = delta.BrickLedger(8, full_share=10.0)
    out = []
    for grid, v, _ in maps:
        message = wire.encode_map(grid, MapMeta(vid, v, 0.0))
        ledger.record(grid, v, message)
        out.append(message)
    return out[0], out[1], ledger.delta_for(1)


def test_a_delta_with_a_base_the_receiver_does_not_hold_is_refused_and_changes_nothing(receiver):
    v1, v2, d12 = held_versions()
    assert send(receiver, d12) == mtp.ACK_DELTA_BASE  # nothing held yet
    assert receiver.received.get(7) is None
    assert send(receiver, v1) == mtp.ACK_OK
    bad_base = bytearray(d12)
    bad_base[52:68] = (5).to_bytes(8, "little") + (9).to_bytes(8, "little")  # v5 -> v9: 1 is held
    assert send(receiver, bytes(bad_base)) == mtp.ACK_DELTA_BASE
    assert bytes(receiver.received.get(7).data) == v1
    assert failures(receiver) == {"delta_base": 2}
    assert send(receiver, d12) == mtp.ACK_OK
    assert bytes(receiver.received.get(7).data) == v2


def test_a_malformed_delta_is_refused_and_changes_nothing(receiver):
    v1, _, d12 = held_versions()
    assert send(receiver, v1) == mtp.ACK_OK
    corrupt = bytearray(d12)
    corrupt[-3] ^= 0x55  # the payload CRC no longer matches
    assert send(receiver, bytes(corrupt)) == mtp.ACK_REJECTED
    huge = bytearray(d12)
    huge[68:72] = (2**32 - 1).to_bytes(4, "little")  # more bricks than the lattice holds
    assert send(receiver, bytes(huge)) == mtp.ACK_REJECTED
    assert send(receiver, d12[:200]) == mtp.ACK_REJECTED  # cut short
    assert bytes(receiver.received.get(7).data) == v1
    assert wait_until(lambda: sum(failures(receiver).values()) == 3, 5)  # counted as the connection ends
    assert failures(receiver) == {"decode": 1, "malformed": 1, "size": 1}


def test_a_receiver_without_deltas_refuses_them():
    svc = real_service(2, deltas=False)
    try:
        v1, _, d12 = held_versions()
        assert send(svc, v1) == mtp.ACK_OK
        assert send(svc, d12) == mtp.ACK_REJECTED
        assert bytes(svc.received.get(7).data) == v1
        assert wait_until(lambda: failures(svc) == {"malformed": 1}, 5)
    finally:
        svc.stop()


def test_a_grid_that_is_not_the_message_is_published_in_full():
    """A caller's mistake (a grid that is not the message's) costs the deltas, never the map."""
    maps = growing_maps(2, seed=4)
    b = real_service(2)
    a = real_service(1, peers=(f"127.0.0.2:{b.address[1]}",))
    try:
        a.publish(maps[0][2], 1, OccupancyGrid.empty((3, 3, 3), 0.1))
        assert a.delta_bytes == 0
        assert wait_until(lambda: b.received.version(1) == 1, 10)
        assert bytes(b.received.get(1).data) == maps[0][2]
    finally:
        a.stop()
        b.stop()

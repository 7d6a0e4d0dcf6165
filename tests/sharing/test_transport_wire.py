"""Real map messages end to end: encode_map on one service, MTP over TCP, inspect + full decode on
the other, stored compressed, decoded again by the consumer; plus thesis type-0 interop and a
message whose payload is corrupted in flight (CRC) being dropped whole."""

import socket

import numpy as np
import pytest
from sharing_support import free_port, settings, wait_until

from coopd.grid import OccupancyGrid
from coopd.sharing import mtp
from coopd.sharing.service import SharingConfig, SharingService, wire_inspect, wire_verifier
from coopd.sharing.transport import PeerLink

wire = pytest.importorskip("coopd.sharing.wire", reason="coopd.sharing.wire (branch formats) not merged yet")


def grid(seed: int, shape=(60, 50, 20)) -> OccupancyGrid:
    rng = np.random.default_rng(seed)
    cells = np.full(shape, -1, dtype=np.int8)
    cells[10:40, 10:40, 2:15] = rng.choice(np.array([0, 0, 0, 20, 100], dtype=np.int8), (30, 30, 13))
    return OccupancyGrid(cells, 0.1, offset=(-30, -25, -2))


def real_service(vid, host, port, peers=(), **transport) -> SharingService:
    s = settings(**transport)
    cfg = SharingConfig(vehicle_id=vid, listen_host=host, port=port, peers=tuple(peers), peer_ports=(port,),
                        scan_period=0.2, transport=s)
    return SharingService(cfg, inspect=wire_inspect, verify=wire_verifier(s.max_cells, s.max_bytes))


@pytest.mark.parametrize("encoding", ["default", "raw"])
def test_real_maps_cross_and_decode_identically(encoding):
    port = free_port("127.0.0.91")
    a = real_service(1, "127.0.0.91", port, ["127.0.0.91-127.0.0.92"]).start()
    b = real_service(2, "127.0.0.92", port, ["127.0.0.91-127.0.0.92"]).start()
    try:
        ga, gb = grid(1), grid(2)
        a.publish(wire.encode_map(ga, wire.MapMeta(1, 5, 1.0), encoding), 5)
        b.publish(wire.encode_map(gb, wire.MapMeta(2, 7, 2.0), encoding), 7)
        assert wait_until(lambda: b.received.version(1) == 5 and a.received.version(2) == 7, 10)
        got, meta = wire.decode_map(b.received.get(1).data)
        assert meta.vehicle_id == 1 and meta.version == 5
        assert np.array_equal(got.cells, ga.cells) and tuple(got.offset) == (-30, -25, -2)
        got2, meta2 = a.decode(2)  # what the merger calls: decoded on demand within the limits
        assert np.array_equal(got2.cells, gb.cells) and meta2.version == 7
        assert a.decode(99) is None
    finally:
        a.stop()
        b.stop()


def test_thesis_type0_message_from_a_thesis_peer_is_accepted():
    svc = real_service(1, "127.0.0.1", 0).start()
    try:
        msg = wire.encode_thesis_map(grid(3), vehicle_id=9, compressed=True)
        with socket.create_connection(svc.address, timeout=2) as s:
            for part in mtp.encode_transfer(msg, svc.config.transport.block_size):
                s.sendall(part)
            assert wait_until(lambda: svc.received.get(9) is not None, 5)
        assert svc.received.get(9).data == msg
    finally:
        svc.stop()


def test_corrupted_payload_is_dropped_whole():
    svc = real_service(1, "127.0.0.1", 0).start()
    try:
        msg = bytearray(wire.encode_map(grid(4), wire.MapMeta(4, 1, 0.0)))
        msg[-10] ^= 0x55  # flipped in flight; the CRC catches it at decode time
        link = PeerLink.connect(*svc.address, svc.config.transport, 4)
        try:
            status, _ = link.send_map(bytes(msg))
        except (OSError, ValueError):
            status = mtp.ACK_REJECTED
        link.close()
        assert status == mtp.ACK_REJECTED
        assert svc.received.all() == []
        assert wait_until(lambda: svc.peers.snapshot()["peers"][0]["failures"].get("decode") == 1, 3)
    finally:
        svc.stop()

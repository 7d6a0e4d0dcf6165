"""Authenticate, then allocate: a keyed server accepts no start frame before the sender proved the
key over both nonces; receive buffers grow with the data that arrived, not with the announcement,
and are charged to the daemon's memory budget."""

import os
import socket

import pytest
from sharing_support import failures, settings, wait_until
from test_transport_hostile import closed_by_server, good_peer_delivers

from coopd.daemon.budget import MIB, MemoryBudget
from coopd.sharing import mtp, swarmkey
from coopd.sharing.transport import INFLIGHT_LEDGER, PeerLink

BS = 256
KEY = b"k" * 32


def read_frame(s: socket.socket) -> bytes:
    buf = b""
    while len(buf) < BS:
        chunk = s.recv(BS - len(buf))
        if not chunk:
            raise ConnectionError("closed")
        buf += chunk
    return buf


def keyed_hello(s: socket.socket, vid: int = 9) -> tuple[bytes, mtp.Hello]:
    """Send a hello that sets the key flag (anyone can), return (our nonce, the server's hello)."""
    nonce = os.urandom(16)
    s.sendall(mtp.hello_frame(mtp.Hello(BS, vid, nonce, True, 5)))
    return nonce, mtp.parse_hello(read_frame(s))


def test_a_keyed_flag_without_a_proof_gets_no_buffer(server):
    svc = server(swarm_key=KEY, max_bytes=4 << 20)
    with socket.create_connection(svc.address, timeout=2) as s:
        keyed_hello(s)
        s.sendall(mtp.start_frame((4 << 20) // BS, BS) + bytes(4096))
        assert closed_by_server(s)
    assert wait_until(lambda: failures(svc).get("auth") == 1, 3), failures(svc)
    assert svc._server.peak_inflight_bytes == 0


def test_a_proof_under_another_key_is_refused(server):
    svc = server(swarm_key=KEY)
    with socket.create_connection(svc.address, timeout=2) as s:
        nonce, theirs = keyed_hello(s)
        tag = swarmkey.proof_tag(b"w" * 32, theirs.nonce, nonce, 9, 5, BS)
        s.sendall(mtp.proof_frame(9, tag, BS) + mtp.start_frame(4, BS))
        assert closed_by_server(s)
    assert wait_until(lambda: failures(svc).get("auth") == 1, 3), failures(svc)
    assert svc._server.peak_inflight_bytes == 0
    good_peer_delivers(svc, 5, 1, swarm_key=KEY)  # a peer with the key proves it and is served


def test_a_replayed_proof_does_not_verify_on_a_new_connection(server):
    svc = server(swarm_key=KEY)
    with socket.create_connection(svc.address, timeout=2) as s:  # a proof made for this connection...
        nonce, theirs = keyed_hello(s)
        proof = mtp.proof_frame(9, swarmkey.proof_tag(KEY, theirs.nonce, nonce, 9, 5, BS), BS)
    with socket.create_connection(svc.address, timeout=2) as s:  # ...sent on another one
        s.sendall(mtp.hello_frame(mtp.Hello(BS, 9, nonce, True, 5)))
        read_frame(s)
        s.sendall(proof + mtp.start_frame(4, BS))
        assert closed_by_server(s)
    # both count: the first connection left without a proof, the second sent a stale one
    assert wait_until(lambda: failures(svc).get("auth") == 2, 3), failures(svc)
    assert svc._server.peak_inflight_bytes == 0


def test_a_wrong_key_peer_that_leaves_after_the_handshake_is_counted_and_logged(server, caplog):
    svc = server(swarm_key=KEY)
    with caplog.at_level("WARNING", logger="coopd.sharing"):
        with pytest.raises(mtp.MtpError, match="did not prove the swarm key"):
            PeerLink.connect(*svc.address, settings(swarm_key=b"w" * 32), 9)
        assert wait_until(lambda: failures(svc).get("auth") == 1, 3), failures(svc)

        def lines():
            return [r.getMessage() for r in caplog.records if "dropped: auth" in r.getMessage()]

        assert wait_until(lambda: len(lines()) == 1, 3)  # logged right after it is counted
    assert "without proving the swarm key" in lines()[0]


def test_announcements_without_data_hold_only_a_small_buffer(server):
    """20 hosts each announce a 64 MiB transfer, send 1 KiB and stall: the server holds what
    arrived rounded up to one step (RESERVE_STEP) each, not 20 x 64 MiB."""
    svc = server(max_bytes=64 << 20, max_inflight_bytes=512 << 20, transfer_base_s=30.0, read_timeout=10.0)
    socks = []
    try:
        for k in range(20):
            s = socket.create_connection(svc.address, timeout=2, source_address=(f"127.0.2.{10 + k}", 0))
            s.sendall(mtp.start_frame((64 << 20) // BS, BS) + bytes(1024))
            socks.append(s)
        assert wait_until(lambda: sum(r["received_bytes"] for r in svc.stats()["receiving"]) == 20 * 1024, 5)
        assert svc._server.peak_inflight_bytes <= 20 * mtp.RESERVE_STEP
        assert failures(svc).get("busy") is None
        good_peer_delivers(svc, 5, 1)
    finally:
        for s in socks:
            s.close()
    assert wait_until(lambda: svc._server.inflight_bytes == 0, 3)


def test_receive_buffers_count_against_the_memory_budget(server):
    ledger = MemoryBudget(2 * MIB, baseline_bytes=0)
    svc = server(max_bytes=16 << 20, max_inflight_bytes=64 << 20, transfer_base_s=30.0)
    svc._server._budget.ledger = ledger  # what SharingService(budget=...) wires in the daemon
    with socket.create_connection(svc.address, timeout=2) as s:
        s.sendall(mtp.start_frame((16 << 20) // BS, BS) + bytes(600 * 1024))
        assert wait_until(lambda: ledger.snapshot()["entries"].get(INFLIGHT_LEDGER, 0) >= 600 * 1024, 3)
        try:  # past 2 MiB the ledger refuses the next step: the transfer is dropped as busy
            s.sendall(bytes(2 * MIB))
        except OSError:
            pass
        assert closed_by_server(s)
    assert wait_until(lambda: failures(svc).get("busy") == 1, 3), failures(svc)
    assert ledger.snapshot()["entries"].get(INFLIGHT_LEDGER) is None and ledger.peak_reserved <= 2 * MIB

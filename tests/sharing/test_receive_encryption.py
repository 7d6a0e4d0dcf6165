"""Keyed transfers are encrypted: an eavesdropper on the radio sees no map byte, and a sealed
transfer from another connection does not open even under a valid HMAC tag."""

import socket

import pytest
import sharing_testmsg as tm
from sharing_support import failures, settings, wait_until
from test_transport import _Recorder

from coopd.sharing import mtp, swarmkey
from coopd.sharing.transport import PeerLink

KEY = b"e" * 32
SECRET = b"the floor plan of the third floor " * 40


def recorded_link(svc, key=KEY, vid: int = 4) -> tuple[PeerLink, _Recorder]:
    rec = _Recorder(socket.create_connection(svc.address, timeout=2))
    link = PeerLink(rec, settings(swarm_key=key), vid)
    link.handshake()
    return link, rec


def test_an_eavesdropper_sees_no_map_bytes(server):
    svc = server(swarm_key=KEY)
    link, rec = recorded_link(svc)
    try:
        assert link.send_map(tm.make(4, 1, SECRET))[0] == mtp.ACK_OK
    finally:
        link.close()
    assert tm.payload(svc.received.get(4).data) == SECRET  # the server decrypted it
    wire = bytes(rec.sent)
    assert SECRET[:16] not in wire and tm.make(4, 1, SECRET)[:13] not in wire


def test_open_links_stay_in_the_clear_for_thesis_interop(server):
    svc = server()
    link, rec = recorded_link(svc, key=None)
    try:
        assert link.send_map(tm.make(4, 1, SECRET))[0] == mtp.ACK_OK
    finally:
        link.close()
    assert SECRET[:16] in bytes(rec.sent)


def test_a_transfer_sealed_for_another_connection_does_not_open(server):
    """A key holder copies a sealed transfer from one connection into another with a valid tag:
    each connection has its own key (HKDF over both nonces), so it does not decrypt."""
    svc = server(swarm_key=KEY)
    first, rec = recorded_link(svc)
    other = swarmkey.seal(first.cipher, 0, tm.make(4, 7, b"copied"))
    first.close()
    link, _ = recorded_link(svc)
    try:
        n = mtp.block_count(len(other), link.s.block_size)
        tag = swarmkey.transfer_tag(KEY, link.peer.nonce, link.nonce, link.seq, n, other,
                                    n * link.s.block_size - len(other))
        link.sock.sendall(b"".join(bytes(b) for b in mtp.encode_transfer(other, link.s.block_size, tag)))
        _, status = mtp.parse_ack(link._recv_exact(link.s.block_size, 2))
    finally:
        link.close()
    assert status == mtp.ACK_REJECTED
    assert wait_until(lambda: failures(svc).get("auth") == 1, 3), failures(svc)
    assert svc.received.all() == []


@pytest.mark.parametrize("change", ["seq", "key", "flip", "truncate"])
def test_sealed_messages_open_only_as_sealed(change):
    cipher = swarmkey.transfer_cipher(KEY, b"s" * 16, b"c" * 16)
    sealed = bytearray(swarmkey.seal(cipher, 5, b"map bytes" * 10) + bytes(30))  # zero padding after
    assert swarmkey.unseal(cipher, 5, sealed) == b"map bytes" * 10
    seq = 5
    if change == "seq":
        seq = 6
    elif change == "key":
        cipher = swarmkey.transfer_cipher(KEY, b"s" * 16, b"d" * 16)
    elif change == "flip":
        sealed[20] ^= 1
    else:
        sealed = sealed[:40]
    with pytest.raises(ValueError):
        swarmkey.unseal(cipher, seq, sealed)

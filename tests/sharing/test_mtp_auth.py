"""Swarm-key tags over MTP transfers and server hellos: any change to a tagged transfer or a signed
hello is refused, and peer-table bookkeeping (restart detection, bounded anonymous failures, grace
period)."""

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from coopd.sharing import mtp, swarmkey
from coopd.sharing.mtp import MtpError, Reassembler
from coopd.sharing.peers import MessageSummary, PeerTable, ReceivedStore

BS = 64
KEY = b"s" * 32
RN, SN = b"r" * 16, b"n" * 16


def tagged(message: bytes, seq: int = 0) -> bytes:
    n = mtp.block_count(len(message), BS)
    tag = swarmkey.transfer_tag(KEY, RN, SN, seq, n, message, n * BS - len(message))
    return b"".join(bytes(p) for p in mtp.encode_transfer(message, BS, tag))


def accepted(raw: bytes, seq: int = 0) -> bool:
    try:
        events = Reassembler(BS).feed(raw)
    except MtpError:
        return False
    for t in events:
        expected = swarmkey.transfer_tag(KEY, RN, SN, seq, t.blocks, t.data)
        if swarmkey.tag_is_valid(expected, t.tag):
            return True
    return False


def test_untouched_tagged_transfer_verifies():
    assert accepted(tagged(b"hello map" * 20))


@settings(max_examples=300, deadline=None)
@given(msg=st.binary(min_size=1, max_size=300), where=st.integers(min_value=0), flip=st.integers(1, 255))
def test_any_flipped_byte_is_refused(msg, where, flip):
    raw = bytearray(tagged(msg))
    raw[where % len(raw)] ^= flip
    assert not accepted(bytes(raw))


def test_replay_under_another_sequence_number_is_refused():
    raw = tagged(b"m" * 100, seq=0)
    assert accepted(raw, seq=0) and not accepted(raw, seq=1)


HELLO_END = mtp.HEAD.size + mtp.HELLO_BODY.size + mtp.HELLO_TAG.size


def signed_hello(vid: int = 2, sender_nonce: bytes = SN) -> bytes:
    tag = swarmkey.hello_tag(KEY, sender_nonce, RN, vid, 77, BS, mtp.PROTOCOL_VERSION)
    return mtp.hello_frame(mtp.Hello(BS, vid, RN, True, 77, tag=tag))


def hello_verifies(frame: bytes, sender_nonce: bytes = SN) -> bool:
    """What a sender checks of a keyed server's hello (PeerLink.handshake)."""
    try:
        (h,) = Reassembler(BS).feed(frame)
    except MtpError:
        return False
    expected = swarmkey.hello_tag(KEY, sender_nonce, h.nonce, h.vehicle_id, h.instance, h.block_size,
                                  h.version)
    return h.keyed and swarmkey.tag_is_valid(expected, h.tag)


def test_a_signed_hello_fits_the_smallest_block_and_verifies():
    frame = signed_hello()
    assert len(frame) == BS == mtp.MIN_BLOCK_SIZE and hello_verifies(frame)
    assert not hello_verifies(mtp.hello_frame(mtp.Hello(BS, 2, RN, True, 77)))  # no tag: v1 or an impostor


@settings(max_examples=200, deadline=None)
@given(where=st.integers(min_value=0, max_value=HELLO_END - 1), flip=st.integers(1, 255))
def test_any_flipped_byte_of_a_signed_hello_is_refused(where, flip):
    """Every field a sender reads, up to the tag's end (reserved flag bits and the bytes after the
    tag are not read: later versions may use them)."""
    if where == 7:
        flip |= mtp.HELLO_FLAG_KEY
    raw = bytearray(signed_hello())
    raw[where] ^= flip
    assert not hello_verifies(bytes(raw))


def test_a_recorded_hello_does_not_verify_for_another_sender_nonce():
    assert not hello_verifies(signed_hello(), sender_nonce=b"x" * 16)


def test_key_loading(tmp_path):
    assert swarmkey.load_key("") is None and swarmkey.load_key(None) is None
    assert swarmkey.load_key("hex:" + "ab" * 16) == b"\xab" * 16
    with pytest.raises(ValueError):
        swarmkey.load_key("short")
    f = tmp_path / "swarm.key"
    f.write_bytes(b"  correct horse battery staple\n")
    assert swarmkey.read_key_file(f) == b"correct horse battery staple"
    f.write_bytes(b"hex:" + b"0f" * 20 + b"\n")
    assert swarmkey.read_key_file(f) == b"\x0f" * 20
    assert swarmkey.read_key_file("") is None
    f.write_bytes(b"x" * 5000)
    with pytest.raises(ValueError):
        swarmkey.read_key_file(f)


def test_peer_restart_resets_what_it_holds():
    t = PeerTable()
    assert t.hello(5, 111)
    t.sent(5, origin=1, version=3, nbytes=10, seconds=0.1)
    assert t.has_version(5, 1) == 3
    assert not t.hello(5, 111)
    assert t.has_version(5, 1) == 3
    assert t.hello(5, 222)  # new instance id: it lost everything
    assert t.has_version(5, 1) == -1


def test_grace_period_and_bounded_anonymous_failures():
    now = [0.0]
    t = PeerTable(clock=lambda: now[0])
    t.seen(5, "10.0.0.5", 7400, connected=True)
    t.seen(6, "10.0.0.6", 7400)
    now[0] = 100.0
    assert t.forget_stale(30.0) == [6]  # 5 is still connected
    t.disconnected(5)
    assert t.forget_stale(30.0) == [5]
    for i in range(1000):
        t.failure("frame", address=f"10.1.{i // 250}.{i % 250}")
    anon = t.snapshot()["unidentified_failures"]
    assert len(anon) <= 257 and sum(c["frame"] for c in anon.values()) == 1000


def test_store_newer_wins_and_unversioned_replaces():
    s = ReceivedStore()
    assert s.offer(MessageSummary(3, 2, 10, 10), b"a")
    assert not s.offer(MessageSummary(3, 1, 10, 10), b"old")
    assert s.offer(MessageSummary(3, 5, 10, 10), b"new") and s.get(3).data == b"new"
    assert s.offer(MessageSummary(4, 0, 10, 10), b"t1") and s.offer(MessageSummary(4, 0, 10, 10), b"t2")
    assert s.get(4).data == b"t2" and s.total_bytes() == 5

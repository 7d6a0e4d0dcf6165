"""MTP framing and reassembly: byte layout, round trips, and every malformed transfer."""

import struct

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from coopd.sharing import mtp
from coopd.sharing.mtp import Hello, MtpError, Reassembler, Transfer

BS = 64


def transfer_bytes(message: bytes, bs: int = BS, tag=None) -> bytes:
    return b"".join(bytes(b) for b in mtp.encode_transfer(message, bs, tag))


def test_start_and_stop_frames_match_the_thesis_byte_tables():
    start = mtp.start_frame(3, 4096)
    assert len(start) == 4096
    assert start[0] == 0x80 and start[1] == 0 and struct.unpack_from("<i", start, 2)[0] == 3
    assert start[6:] == bytes(4090)
    stop = mtp.stop_frame(3, 4096)
    assert stop[:2] == b"\x80\x01" and struct.unpack_from("<i", stop, 2)[0] == 3 and stop[6:] == bytes(4090)


def test_transfer_is_start_blocks_stop_with_zero_padding():
    msg = bytes(range(1, 101))  # 100 bytes -> 2 blocks of 64
    raw = transfer_bytes(msg)
    assert len(raw) == 4 * BS
    assert raw[BS:BS + 100] == msg and raw[BS + 100:3 * BS] == bytes(28)


def test_tag_travels_in_stop_frame_spare_bytes():
    tag = bytes(range(32))
    stop = mtp.stop_frame(2, BS, tag)
    assert stop[6] == mtp.TAG_HMAC_SHA256 and stop[7:39] == tag and stop[39:] == bytes(BS - 39)
    (t,) = Reassembler(BS).feed(transfer_bytes(b"x" * 70, tag=tag))
    assert t.tag == tag


@settings(max_examples=150, deadline=None)
@given(msg=st.binary(min_size=1, max_size=700), bs=st.sampled_from([64, 100, 256]),
       cuts=st.lists(st.integers(min_value=1, max_value=300), max_size=40))
def test_round_trip_any_chunking(msg, bs, cuts):
    raw = transfer_bytes(msg, bs) * 2  # two transfers back to back on one connection
    r = Reassembler(bs)
    events, pos = [], 0
    for c in cuts + [len(raw)]:
        events += r.feed(raw[pos:pos + c])
        pos += c
        if pos >= len(raw):
            break
    assert len(events) == 2
    for t in events:
        assert isinstance(t, Transfer)
        assert t.blocks == mtp.block_count(len(msg), bs)
        assert bytes(t.data[:len(msg)]) == msg and not any(t.data[len(msg):])
    assert not r.in_transfer


@settings(max_examples=300, deadline=None)
@given(junk=st.binary(min_size=1, max_size=600))
def test_random_bytes_never_crash_or_publish(junk):
    r = Reassembler(BS, max_bytes=4096)
    try:
        events = r.feed(junk)
    except MtpError as e:
        assert e.cause in {"frame", "count", "oversize", "block_size"}
        return
    assert not any(isinstance(e, Transfer) for e in events) or junk[:2] == b"\x80\x00"


def test_random_bytes_are_a_frame_error():
    with pytest.raises(MtpError) as e:
        Reassembler(BS).feed(b"GET / HTTP/1.1\r\n" + bytes(100))
    assert e.value.cause == "frame"


def test_truncated_transfer_publishes_nothing_and_releases():
    reserved = []
    r = Reassembler(BS, reserve=lambda n: reserved.append(n) or True, release=lambda n: reserved.append(-n))
    raw = transfer_bytes(b"y" * 200)
    assert r.feed(raw[:-1]) == []
    assert r.in_transfer and r.received_bytes == 4 * BS and sum(reserved) == 4 * BS
    r.close()
    assert sum(reserved) == 0


@pytest.mark.parametrize("announced,sent,stop_count", [(3, 2, 2), (2, 2, 3), (3, 3, 2), (2, 1, 1)])
def test_miscounted_transfer_is_dropped(announced, sent, stop_count):
    raw = mtp.start_frame(announced, BS) + b"\x01" * (sent * BS) + mtp.stop_frame(stop_count, BS)
    raw += b"\x01" * BS * 2 + mtp.stop_frame(stop_count, BS)  # whatever follows
    with pytest.raises(MtpError) as e:
        Reassembler(BS).feed(raw)
    assert e.value.cause == "count"


def test_more_blocks_than_announced_is_a_count_error():
    raw = mtp.start_frame(1, BS) + b"\x07" * (2 * BS) + mtp.stop_frame(2, BS)
    with pytest.raises(MtpError) as e:
        Reassembler(BS).feed(raw)
    assert e.value.cause == "count"


def test_stop_without_start_and_start_inside_transfer():
    for raw in (mtp.stop_frame(0, BS), mtp.start_frame(1, BS) + b"a" * BS + mtp.start_frame(1, BS)):
        with pytest.raises(MtpError) as e:
            Reassembler(BS).feed(raw)
        assert e.value.cause == "count"


@pytest.mark.parametrize("count", [2**31 - 1, 1 << 20])
def test_huge_announcement_is_refused_before_allocating(count):
    r = Reassembler(BS, max_bytes=1 << 20)
    with pytest.raises(MtpError) as e:
        r.feed(mtp.start_frame(count, BS)[:6])  # refused on the 6 header bytes alone
    assert e.value.cause == "oversize"


def test_start_announcing_2_pow_31_blocks_wraps_negative_and_is_refused():
    frame = bytearray(BS)
    frame[0], frame[1] = 0x80, 0
    frame[2:6] = (2**31).to_bytes(4, "little")  # int32: -2**31
    with pytest.raises(MtpError) as e:
        Reassembler(BS).feed(frame)
    assert e.value.cause == "frame"


def test_zero_block_transfer_is_refused():
    with pytest.raises(MtpError):
        Reassembler(BS).feed(mtp.start_frame(0, BS))


def test_reserve_refusal_is_busy():
    r = Reassembler(BS, reserve=lambda n: False, release=lambda n: None)
    r.feed(mtp.start_frame(4, BS))  # buffers are reserved as data arrives, not on the announcement
    with pytest.raises(MtpError) as e:
        r.feed(b"\x00")
    assert e.value.cause == "busy"


def test_block_size_mismatch_fails_clearly_with_hello():
    hello = mtp.hello_frame(Hello(block_size=128, vehicle_id=7, nonce=b"n" * 16, keyed=False))
    with pytest.raises(MtpError) as e:
        Reassembler(BS).feed(hello)
    assert e.value.cause == "block_size" and "128" in str(e.value) and "64" in str(e.value)


def test_block_size_mismatch_without_hello_is_caught_by_padding():
    # a thesis peer with BS=64 talking to a receiver with BS=256: its data lands in our start frame
    raw = transfer_bytes(b"\x05" * 300, bs=64)
    with pytest.raises(MtpError) as e:
        Reassembler(256).feed(raw)
    assert "block size" in str(e.value)


def test_hello_round_trip_and_only_first():
    h = Hello(block_size=BS, vehicle_id=-5, nonce=bytes(range(16)), keyed=True)
    r = Reassembler(BS)
    (got,) = r.feed(mtp.hello_frame(h))
    assert got == h
    with pytest.raises(MtpError):
        r.feed(mtp.hello_frame(h))


def test_malformed_stop_spare_bytes():
    stop = bytearray(mtp.stop_frame(1, BS))
    stop[20] = 9
    with pytest.raises(MtpError):
        Reassembler(BS).feed(mtp.start_frame(1, BS) + b"z" * BS + bytes(stop))


def test_ack_frame_round_trip_and_refused_by_receiver():
    ack = mtp.ack_frame(5, mtp.ACK_STALE, BS)
    assert mtp.parse_ack(ack) == (5, mtp.ACK_STALE)
    with pytest.raises(MtpError):
        Reassembler(BS).feed(ack)
    with pytest.raises(MtpError):
        mtp.parse_ack(mtp.start_frame(1, BS))


def test_block_size_setting_is_checked():
    for bad in (0, 10, mtp.MAX_BLOCK_SIZE + 1):
        with pytest.raises(ValueError):
            Reassembler(bad)


def test_offer_frame_needs_a_hello_and_round_trips():
    offer = mtp.offer_frame(origin=7, version=2**40 + 3, block_size=BS)
    assert offer[:2] == b"\x80\x04" and struct.unpack_from("<iQ", offer, 2) == (7, 2**40 + 3)
    with pytest.raises(MtpError):
        Reassembler(BS).feed(offer)  # a thesis-format connection never offers
    r = Reassembler(BS)
    r.feed(mtp.hello_frame(Hello(BS, 1, b"n" * 16, False)))
    assert r.feed(offer) == [mtp.Offer(7, 2**40 + 3)]
    bad = bytearray(offer)
    bad[-1] = 1
    with pytest.raises(MtpError):
        r.feed(bytes(bad))

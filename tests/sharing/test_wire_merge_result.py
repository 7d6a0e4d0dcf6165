"""Merge-result messages (wire type 2): round trip, and every malformed or oversized one refused."""

import struct
import zlib

import numpy as np
import pytest

from coopd.geometry import rigid, rotation_z
from coopd.sharing import wire
from coopd.sharing.service import wire_inspect


def _edge(a=1, b=2, yaw=0.3, shift=(4.0, -2.0, 0.1), **kw):
    fields = dict(score=0.97, overlap=0.4, version_a=12, version_b=7, flags=wire.EDGE_FULL) | kw
    return wire.MergeEdge(a, b, rigid(rotation_z(yaw), shift), **fields)


def _message(edges=None, **kw):
    fields = dict(vehicle_id=1, version=5, stamp=1.7e9) | kw
    return wire.MergeResultMessage(edges=tuple(edges if edges is not None else [_edge(), _edge(1, 3, -2.0)]),
                                   **fields)


def _recrc(data: bytes) -> bytes:
    """data with its header CRC rewritten to match its (tampered) edges."""
    head = bytearray(data[:wire.RESULT_HEADER.size])
    struct.pack_into("<I", head, wire.RESULT_HEADER.size - 4, zlib.crc32(data[wire.RESULT_HEADER.size:]))
    return bytes(head) + data[wire.RESULT_HEADER.size:]


def test_round_trip_keeps_every_field_and_the_float64_transform():
    msg = _message()
    data = wire.encode_merge_result(msg)
    assert len(data) == msg.size == wire.RESULT_HEADER.size + 2 * wire.RESULT_EDGE.size == 360
    back = wire.decode_merge_result(data)
    assert (back.vehicle_id, back.version, back.stamp) == (1, 5, 1.7e9)
    for e, f in zip(msg.edges, back.edges, strict=True):
        assert (f.a, f.b, f.version_a, f.version_b, f.flags) == (e.a, e.b, e.version_a, e.version_b, e.flags)
        assert np.array_equal(f.transform, e.transform)  # bit-exact float64
        assert f.score == pytest.approx(e.score, abs=1e-6) and f.overlap == pytest.approx(e.overlap, abs=1e-6)
    s = wire_inspect(data)
    assert (s.vehicle_id, s.version, s.size, s.cells, s.kind) == (1, 5, 360, 0, "result")
    empty = wire.encode_merge_result(_message([]))
    assert wire.decode_merge_result(empty).edges == ()
    with pytest.raises(wire.UnknownMessageType, match="merge result"):
        wire.peek(data)  # not a map: the map paths refuse it


def test_encoder_refuses_what_a_decoder_would_refuse():
    with pytest.raises(wire.WireError, match="at most 64"):
        wire.encode_merge_result(_message([_edge(1, 2 + i) for i in range(wire.MAX_EDGES + 1)]))
    bent = _edge()
    bent.transform[0, 1] += 0.1
    for bad in (bent, _edge(2, 2), _edge(score=1.5), _edge(shift=(2e6, 0, 0))):
        with pytest.raises(wire.WireError):
            wire.encode_merge_result(_message([bad]))
    assert len(wire.encode_merge_result(_message([_edge(1, 2 + i) for i in range(64)]))) == 32 + 64 * 164


def _set(data: bytes, fmt: str, offset: int, value) -> bytes:
    out = bytearray(data)
    struct.pack_into(fmt, out, offset, value)
    return bytes(out)


EDGE0 = wire.RESULT_HEADER.size


@pytest.mark.parametrize("case, tamper, match", [
    ("truncated", lambda d: d[:-1], "announces"),
    ("trailing", lambda d: d + b"\0", "announces"),
    ("short header", lambda d: d[:20], "needs 32 bytes"),
    ("crc", lambda d: d[:-5] + bytes([d[-5] ^ 1]) + d[-4:], "CRC"),
    ("format", lambda d: _set(d, "<B", 1, 2), "newer"),
    ("format 0", lambda d: _set(d, "<B", 1, 0), "does not exist"),
    ("header length", lambda d: _set(d, "<H", 2, 40), "header length"),
    ("edge size", lambda d: _set(d, "<H", 26, 100), "edge size"),
    ("count", lambda d: _set(d, "<H", 24, 65), "at most 64"),
    ("count over data", lambda d: _set(d, "<H", 24, 3), "announces"),
    ("stamp", lambda d: _set(d, "<d", 16, float("nan")), "timestamp"),
    ("nan transform", lambda d: _recrc(_set(d, "<d", EDGE0 + 8, float("nan"))), "finite"),
    ("scaled rotation", lambda d: _recrc(_set(d, "<d", EDGE0 + 8, 2.0)), "not rigid"),
    ("far translation", lambda d: _recrc(_set(d, "<d", EDGE0 + 8 + 24, 1e9)), "out of range"),
    ("self edge", lambda d: _recrc(_set(d, "<i", EDGE0 + 4, 1)), "itself"),
    ("score", lambda d: _recrc(_set(d, "<f", EDGE0 + 136, float("inf"))), "outside 0..1"),
    ("flags", lambda d: _recrc(_set(d, "<B", EDGE0 + 160, 0x82)), "flags"),
    ("type", lambda d: _set(d, "<b", 0, 1), "not a merge result"),
])
def test_malformed_messages_are_refused_with_a_clear_error(case, tamper, match):
    data = wire.encode_merge_result(_message())
    with pytest.raises(wire.WireError, match=match):
        wire.decode_merge_result(tamper(data))


def test_oversized_count_is_refused_before_reading_the_edges():
    head = wire.RESULT_HEADER.pack(wire.MSG_MERGE_RESULT, 1, 32, 1, 1, 0.0, 65535, wire.RESULT_EDGE.size, 0)
    with pytest.raises(wire.WireError, match="at most 64"):
        wire.peek_merge_result(head)
    with pytest.raises(wire.WireError, match="at most 64"):
        wire_inspect(head)

"""Map messages (notes §5): byte tables field by field, round trips, hostile headers refused."""

import struct
import zlib

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from coopd.grid import OccupancyGrid
from coopd.sharing import codec
from coopd.sharing.wire import (
    COOPD_HEADER,
    DecodeLimits,
    MapMeta,
    MessageVersionError,
    UnknownMessageType,
    WireError,
    decode_map,
    encode_map,
    encode_thesis_map,
    negotiate,
    peek,
)
from tests.sharing.realistic_maps import building_map


def small_grid(offset=(-3, 4, -1)) -> OccupancyGrid:
    cells = np.full((4, 3, 5), -1, np.int8)
    cells[1, 1, :] = [0, 0, 0, 100, 100]
    cells[2, 0, 1] = -2
    cells[3, 2, 4] = 42
    return OccupancyGrid(cells, 0.1, offset)


def test_thesis_header_byte_table():
    grid = small_grid()
    msg = encode_thesis_map(grid, vehicle_id=0x01020304, compressed=True)
    payload = codec.compress(grid.flat).tobytes()
    expected = (bytes([0])                                   # 0: message type 0 = map
                + bytes([0x04, 0x03, 0x02, 0x01])            # 1-4: vehicle id, int32 LE
                + bytes([1])                                 # 5: map type 1 = 3D
                + bytes([4, 0, 0, 0, 3, 0, 0, 0, 5, 0, 0, 0])  # 6-17: m_x, m_y, m_z
                + bytes([0xCD, 0xCC, 0xCC, 0x3D])            # 18-21: float32 0.1 LE
                + bytes([1])                                 # 22: is compressed
                + len(payload).to_bytes(4, "little"))        # 23-26: data size
    assert msg[:27] == expected
    assert msg[27:] == payload and len(msg) == 27 + len(payload)


def test_thesis_message_read_from_hand_built_bytes():
    cells = np.array([-1] * 200 + [0, 0, 100], np.int8)
    data = codec.compress(cells).tobytes()
    msg = struct.pack("<bibiiifbi", 0, 7, 1, 1, 1, 203, 0.05, 1, len(data)) + data
    grid, meta = decode_map(msg)
    assert grid.shape == (1, 1, 203) and grid.resolution == 0.05
    assert tuple(grid.offset) == (0, 0, 0)
    assert np.array_equal(grid.flat, cells)
    assert meta.vehicle_id == 7 and meta.version == 0
    raw = struct.pack("<bibiiifbi", 0, 7, 0, 2, 2, 1, 0.2, 0, 4) + bytes([0, 1, 2, 0xFF])
    grid, _ = decode_map(raw)
    assert grid.shape == (2, 2, 1) and grid.flat.tolist() == [0, 1, 2, -1]


@pytest.mark.parametrize("compressed", [True, False])
def test_thesis_round_trip_is_byte_exact(compressed):
    grid = small_grid(offset=(0, 0, 0))
    msg = encode_thesis_map(grid, 3, compressed)
    back, meta = decode_map(msg)
    assert np.array_equal(back.cells, grid.cells) and meta.vehicle_id == 3
    assert encode_thesis_map(back, 3, compressed) == msg


def test_coopd_header_byte_table():
    grid = small_grid(offset=(-3, 4, -1))
    meta = MapMeta(vehicle_id=9, version=258, stamp=1.5)
    msg = encode_map(grid, meta, encoding="thesis")
    payload = codec.compress(grid.flat).tobytes()
    f64 = lambda v: struct.pack("<d", v)  # noqa: E731
    i32 = lambda v: struct.pack("<i", v)  # noqa: E731
    expected = (bytes([1, 1]) + (92).to_bytes(2, "little")      # 0 type, 1 version, 2-3 header length
                + i32(9) + bytes([1, 1]) + bytes([0, 0])         # 4-7 vehicle, 8 map type, 9 enc, 10-11 flags
                + i32(4) + i32(3) + i32(5)                       # 12-23 m_x, m_y, m_z
                + i32(-3) + i32(4) + i32(-1)                     # 24-35 offset (cells)
                + f64(0.1)                                       # 36-43 resolution
                + f64(-3 * 0.1) + f64(4 * 0.1) + f64(-1 * 0.1)   # 44-67 origin (m)
                + (258).to_bytes(8, "little")                    # 68-75 map version
                + f64(1.5)                                       # 76-83 stamp
                + len(payload).to_bytes(4, "little")             # 84-87 payload size
                + zlib.crc32(payload).to_bytes(4, "little"))     # 88-91 CRC-32
    assert COOPD_HEADER.size == 92
    assert msg[:92] == expected and msg[92:] == payload


@pytest.mark.parametrize("encoding", ["default", "raw", "thesis", "thesis-zstd", "planes-zstd"])
def test_coopd_round_trip(encoding):
    cells = building_map((60, 50, 20), explored=0.4, seed=3)
    grid = OccupancyGrid(cells, 0.05, (-30, -25, -2))
    meta = MapMeta(vehicle_id=-5, version=2**40 + 1, stamp=1_763_000_000.25)
    msg = encode_map(grid, meta, encoding)
    back, back_meta = decode_map(msg, DecodeLimits(max_cells=grid.size, max_bytes=len(msg)))
    assert back_meta == meta
    assert back.resolution == 0.05 and tuple(back.offset) == (-30, -25, -2)
    assert np.array_equal(back.cells, grid.cells)
    info = peek(msg[:100])
    assert info.shape == grid.shape and info.total_size == len(msg)


def test_limits_refuse_before_decoding():
    grid = OccupancyGrid(np.full((10, 10, 10), -1, np.int8), 0.1)
    msg = encode_map(grid, MapMeta(1))
    with pytest.raises(WireError, match="cells exceeds"):
        decode_map(msg, DecodeLimits(max_cells=999))
    with pytest.raises(WireError, match="bytes exceeds"):
        decode_map(msg, DecodeLimits(max_bytes=len(msg) - 1))
    with pytest.raises(WireError, match="bytes exceeds"):  # from the header alone, as MTP will
        peek(msg[:92]).check(DecodeLimits(max_bytes=len(msg) - 1))
    peek(msg[:92]).check(DecodeLimits(max_cells=1000, max_bytes=len(msg)))


def test_newer_version_rejected_clearly():
    msg = bytearray(encode_map(small_grid(), MapMeta(1)))
    msg[1] = 2
    with pytest.raises(MessageVersionError, match="newer than this coopd reads"):
        decode_map(bytes(msg))
    with pytest.raises(MessageVersionError):
        peek(bytes(msg[:4]))


def test_longer_header_of_same_version_is_skipped():
    msg = encode_map(small_grid(), MapMeta(1), "thesis")
    header, payload = bytearray(msg[:92]), msg[92:]
    header[2:4] = (100).to_bytes(2, "little")
    grid, _ = decode_map(bytes(header) + bytes(8) + payload)
    assert np.array_equal(grid.cells, small_grid().cells)


@pytest.mark.parametrize("mutate, error, message", [
    (lambda m: m.__setitem__(0, 3), UnknownMessageType, "reserved"),
    (lambda m: m.__setitem__(0, 0x80), UnknownMessageType, "MTP"),
    (lambda m: m.__setitem__(0, 77), UnknownMessageType, "unknown message type"),
    (lambda m: m.__setitem__(9, 200), WireError, "encoding id"),
    (lambda m: m.__setitem__(10, 1), WireError, "flags"),
    (lambda m: m.__setitem__(8, 0), WireError, "2D map"),
    (lambda m: m.__setitem__(slice(12, 16), (0).to_bytes(4, "little")), WireError, "non-positive"),
    (lambda m: m.__setitem__(slice(44, 52), struct.pack("<d", 5.0)), WireError, "origin"),
    (lambda m: m.__setitem__(-1, m[-1] ^ 1), WireError, "CRC"),
    (lambda m: m.extend(b"\0"), WireError, "announces"),
    (lambda m: m.__delitem__(slice(-1, None)), WireError, "announces"),
])
def test_hostile_coopd_headers(mutate, error, message):
    msg = bytearray(encode_map(small_grid(), MapMeta(1), "thesis"))
    mutate(msg)
    with pytest.raises(error, match=message):
        decode_map(bytes(msg))


def test_zstd_payload_must_declare_a_bounded_size():
    import zstandard
    grid = small_grid()
    msg = bytearray(encode_map(grid, MapMeta(1), "thesis-zstd"))
    bomb = zstandard.ZstdCompressor().compress(bytes(grid.size + 1))
    header = bytearray(msg[:92])
    header[84:88] = len(bomb).to_bytes(4, "little")
    header[88:92] = zlib.crc32(bomb).to_bytes(4, "little")
    with pytest.raises(WireError, match="declares"):
        decode_map(bytes(header) + bomb)


def test_negotiation_prefers_planes_and_falls_back_to_thesis():
    assert negotiate(["raw", "thesis", "thesis-zstd", "planes-zstd"]) == "planes-zstd"
    assert negotiate(["raw", "thesis", "thesis-zstd"]) == "thesis-zstd"
    assert negotiate(["thesis"]) == "thesis"
    assert negotiate(["something-new"]) == "thesis"


def _decode_or_wire_error(data: bytes):
    try:
        grid, _ = decode_map(data, DecodeLimits(max_cells=100_000, max_bytes=10_000))
    except WireError:
        return None
    assert grid.size <= 100_000
    return grid


@pytest.mark.timeout(120)  # "never hang": a stuck decoder fails here, not at the global limit
@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=300))
def test_fuzz_random_messages(data):
    _decode_or_wire_error(data)


@pytest.mark.timeout(120)  # "never hang": a stuck decoder fails here, not at the global limit
@settings(max_examples=300, deadline=None)
@given(st.sampled_from(["thesis0", "raw", "thesis", "thesis-zstd", "planes-zstd"]), st.data())
def test_fuzz_mutated_messages(kind, data):
    grid = small_grid(offset=(0, 0, 0))
    msg = bytearray(encode_thesis_map(grid, 1) if kind == "thesis0" else encode_map(grid, MapMeta(1), kind))
    for _ in range(data.draw(st.integers(1, 4))):
        msg[data.draw(st.integers(0, len(msg) - 1))] = data.draw(st.integers(0, 255))
    if data.draw(st.booleans()):
        del msg[data.draw(st.integers(0, len(msg))):]
    _decode_or_wire_error(bytes(msg))


@pytest.mark.parametrize("encoding", ["raw", "thesis", "thesis-zstd", "planes-zstd"])
def test_hostile_payload_is_refused_before_allocating_the_map(encoding):
    import tracemalloc
    n = 2_000_000
    grid = OccupancyGrid(np.full((200, 100, 100), -1, np.int8), 0.1)
    msg = bytearray(encode_map(grid, MapMeta(1), encoding)[:92])
    garbage = bytes(range(256)) * 4
    msg[84:88] = len(garbage).to_bytes(4, "little")
    msg[88:92] = zlib.crc32(garbage).to_bytes(4, "little")
    tracemalloc.start()
    try:
        with pytest.raises(WireError):
            decode_map(bytes(msg) + garbage, DecodeLimits(max_cells=n))
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < n // 4


@pytest.mark.parametrize("encoding", ["raw", "thesis", "thesis-zstd", "planes-zstd"])
def test_encoder_refuses_cells_a_decoder_would_refuse(encoding):
    cells = np.zeros((2, 2, 2), np.int8)
    cells[1, 1, 1] = 120
    with pytest.raises(ValueError):
        encode_map(OccupancyGrid(cells, 0.1), MapMeta(1), encoding)

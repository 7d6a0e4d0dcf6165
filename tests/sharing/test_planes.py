"""The planes-zstd encoding: lossless for every cell stream, hostile payloads refused."""

import struct

import numpy as np
import pytest
import zstandard
from hypothesis import given, settings
from hypothesis import strategies as st

from coopd.sharing.planes import PlanesError, decode, encode
from tests.sharing.realistic_maps import building_map


@settings(max_examples=150, deadline=None)
@given(st.lists(st.integers(-2, 100), max_size=300).map(lambda v: np.array(v, dtype=np.int8)))
def test_round_trip_arbitrary_cells(cells):
    assert np.array_equal(decode(encode(cells), cells.size), cells)


@pytest.mark.parametrize("seed", [0, 7])
def test_round_trip_realistic_map_and_smaller_than_zstd19(seed):
    cells = building_map((100, 90, 40), explored=0.2, seed=seed).reshape(-1)
    payload = encode(cells)
    assert np.array_equal(decode(payload, cells.size), cells)
    assert len(payload) < len(zstandard.ZstdCompressor(level=19).compress(cells.tobytes()))


def test_rejects_cells_outside_range():
    with pytest.raises(ValueError, match="cell 1"):
        encode(np.array([0, 101, 0], np.int8))


def _payload(plane: bytes, nibbles: bytes, raw: bytes) -> bytes:
    zc = zstandard.ZstdCompressor()
    frames = [zc.compress(x) for x in (plane, nibbles, raw)]
    return struct.pack("<III", *map(len, frames)) + b"".join(frames)


@pytest.mark.parametrize("parts, n, message", [
    ((b"\x03", b"", b""), 4, "escape nibbles"),            # escape without a nibble
    ((b"\x01", b"\x05", b""), 4, "escape nibbles"),        # nibble nobody uses
    ((b"\x03", b"\x0c", b""), 4, "undefined escape nibble"),
    ((b"\x03", b"\x0f", b""), 4, "raw bytes"),             # raw escape, no raw byte
    ((b"\x03", b"\x0f", b"\x65"), 4, "outside the cell range"),
    ((b"\x40", b"", b""), 3, "beyond the last cell"),
    ((b"\x00\x00", b"", b""), 4, "expected 1"),           # plane of the wrong size
])
def test_rejects_inconsistent_streams(parts, n, message):
    with pytest.raises(PlanesError, match=message):
        decode(_payload(*parts), n)


def test_rejects_bombs_and_framing_errors():
    big = zstandard.ZstdCompressor().compress(bytes(10_000))
    bomb = struct.pack("<III", 1, 1, len(big)) + b"\0\0" + big
    with pytest.raises(PlanesError):
        decode(bomb, 4)
    with pytest.raises(PlanesError, match="add up"):
        decode(encode(np.zeros(8, np.int8)) + b"x", 8)
    with pytest.raises(PlanesError, match="shorter"):
        decode(b"\0", 8)


@pytest.mark.timeout(120)  # "never hang": a stuck decoder fails here, not at the global limit
@settings(max_examples=200, deadline=None)
@given(st.data())
def test_fuzz_mutated_payloads(data):
    cells = building_map((12, 10, 8), explored=0.8, seed=data.draw(st.integers(0, 3))).reshape(-1)
    payload = bytearray(encode(cells))
    for _ in range(data.draw(st.integers(1, 3))):
        payload[data.draw(st.integers(0, len(payload) - 1))] = data.draw(st.integers(0, 255))
    try:
        out = decode(bytes(payload), cells.size)
    except PlanesError:
        return
    assert out.size == cells.size and out.min() >= -2 and out.max() <= 100

"""The thesis codec (notes §4): canonical output, exact inverse, hostile streams rejected."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from coopd.sharing.codec import CodecError, StreamCompressor, compress, decompress
from tests.sharing.realistic_maps import building_map

CELL_VALUES = st.integers(-2, 100)


def thesis_reference(cells) -> list[int]:
    """The thesis algorithm written out literally: occurrence pass, then sequence passes."""
    cells = [int(c) for c in cells]
    out, i = [], 0
    while i < len(cells):  # level 0: runs >= 3 -> (-10, v, c) pieces of at most 127
        j = i
        while j < len(cells) and cells[j] == cells[i]:
            j += 1
        n = j - i
        if n < 3:
            out.extend(cells[i:j])
        else:
            while n > 0:
                out.append((-10, cells[i], min(n, 127)))
                n -= min(n, 127)
        i = j
    level = 1
    while True:  # level L: >= 2 consecutive (-10-(L-1), v, 127) -> (-10-L, v, k), k <= 127
        new, i, changed = [], 0, False
        while i < len(out):
            item = out[i]
            full = isinstance(item, tuple) and item[0] == -10 - (level - 1) and item[2] == 127
            j = i
            while full and j < len(out) and out[j] == item:
                j += 1
            if full and j - i >= 2:
                k = j - i
                while k > 0:
                    piece = min(k, 127)
                    new.append((-10 - level, item[1], piece) if piece >= 2 else item)
                    k -= piece
                changed = True
                i = j
            else:
                new.append(item)
                i += 1
        out = new
        if not changed:
            break
        level += 1
    flat = []
    for item in out:
        flat.extend(item if isinstance(item, tuple) else (item,))
    return flat


def runs_strategy(max_run: int):
    """Arrays built from runs, so long runs and level >= 1 sequences actually occur."""
    run = st.tuples(CELL_VALUES, st.integers(1, max_run))
    return st.lists(run, max_size=12).map(
        lambda runs: np.concatenate([np.full(n, v, np.int8) for v, n in runs] or [np.zeros(0, np.int8)]))


@settings(max_examples=150, deadline=None)
@given(st.lists(CELL_VALUES, max_size=400).map(lambda v: np.array(v, dtype=np.int8)))
def test_round_trip_arbitrary_cells(cells):
    stream = compress(cells)
    assert stream.dtype == np.int8
    assert not np.any(stream == -128)
    assert len(stream) <= len(cells)
    assert np.array_equal(decompress(stream, cells.size), cells)


@settings(max_examples=60, deadline=None)
@given(runs_strategy(40_000))
def test_matches_literal_thesis_passes(cells):
    stream = compress(cells)
    assert stream.tolist() == thesis_reference(cells)
    assert np.array_equal(decompress(stream, cells.size), cells)
    assert np.array_equal(compress(decompress(stream, cells.size)), stream)


def test_level_3_sequence_and_pieces():
    n = 2 * 127**3 + 127**2 + 2 * 127 + 1
    stream = compress(np.full(n, -1, np.int8))
    # digits (2, 1, 2, 1): level 3 x2, lone level-1 full triple, level 1 x2, level-0 remainder
    assert stream.tolist() == [-13, -1, 2, -11, -1, 127, -11, -1, 2, -10, -1, 1]
    assert np.array_equal(decompress(stream, n), np.full(n, -1, np.int8))


def test_short_runs_stay_literals_and_remainders_are_triples():
    assert compress(np.array([5, 5, 7], np.int8)).tolist() == [5, 5, 7]
    assert compress(np.array([5, 5, 5], np.int8)).tolist() == [-10, 5, 3]
    assert compress(np.full(128, 0, np.int8)).tolist() == [-10, 0, 127, -10, 0, 1]
    assert compress(np.full(254, 0, np.int8)).tolist() == [-11, 0, 2]


@pytest.mark.parametrize("seed", [0, 1])
def test_round_trip_realistic_map(seed):
    cells = building_map((120, 110, 40), explored=0.3, seed=seed).reshape(-1)
    stream = compress(cells)
    assert len(stream) * 2 < cells.size
    assert not np.any(stream == -128)
    assert np.array_equal(decompress(stream.tobytes(), cells.size), cells)


@settings(max_examples=40, deadline=None)
@given(runs_strategy(3000), st.lists(st.integers(1, 5000), max_size=6))
def test_stream_compressor_equals_whole(cells, cuts):
    bounds = np.cumsum([0, *cuts])
    parts = np.split(cells, [int(b) for b in bounds if 0 < b < cells.size])
    sc = StreamCompressor()
    chunks = [sc.feed(p) for p in parts] + [sc.finish()]
    assert np.concatenate(chunks).tolist() == compress(cells).tolist()


@pytest.mark.parametrize("bad", [-3, -9, 101, 127, -128])
def test_compress_rejects_values_outside_cell_range(bad):
    cells = np.array([0, 0, bad, 1], np.int8)
    with pytest.raises(CodecError, match="cell 2"):
        compress(cells)


def test_compress_rejects_non_int8():
    with pytest.raises(CodecError):
        compress(np.zeros(4, np.int16))


@pytest.mark.parametrize("stream, expected, message", [
    ([-10, 0], 5, "ends inside"),
    ([-10], 5, "ends inside"),
    ([-10, 0, 5, 1], 5, "beyond"),
    ([-10, 0, 4], 5, "fewer"),
    ([-5, 0, 3], 3, "neither"),
    ([101], 1, "neither"),
    ([-128, 0, 0], 3, "neither"),
    ([-10, 0, 0], 0, "count 0"),
    ([-10, 0, -4], 4, "count -4"),
    ([-10, -5, 3], 3, "run value -5"),
    ([-10, 120, 3], 3, "run value 120"),
    ([-127, 0, 127], 10**6, "beyond"),
])
def test_decompress_rejects_malformed(stream, expected, message):
    with pytest.raises(CodecError, match=message):
        decompress(np.array(stream, np.int8), expected)


def test_decompress_checks_before_allocating():
    # A 3-byte stream announcing 2**40 cells must be rejected without a 1 TB allocation.
    with pytest.raises(CodecError, match="fewer"):
        decompress(np.array([-13, -1, 1], np.int8), 1 << 40)
    with pytest.raises(CodecError, match="outside"):
        decompress(np.array([-1], np.int8), (1 << 40) + 1)
    with pytest.raises(CodecError, match="outside"):
        decompress(b"", -1)


def _expand_or_error(stream: np.ndarray, expected: int):
    try:
        out = decompress(stream, expected)
    except CodecError:
        return None
    assert out.size == expected and out.dtype == np.int8
    assert out.min(initial=0) >= -2 and out.max(initial=0) <= 100
    return out


@pytest.mark.timeout(120)  # "never hang": a stuck decoder fails here, not at the global limit
@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=200), st.integers(0, 100_000))
def test_fuzz_random_streams(data, expected):
    _expand_or_error(np.frombuffer(data, np.int8), expected)


@pytest.mark.timeout(120)  # "never hang": a stuck decoder fails here, not at the global limit
@settings(max_examples=200, deadline=None)
@given(runs_strategy(20_000), st.data())
def test_fuzz_mutated_streams(cells, data):
    stream = compress(cells).copy()
    if stream.size:
        for _ in range(data.draw(st.integers(1, 4))):
            pos = data.draw(st.integers(0, stream.size - 1))
            stream[pos] = data.draw(st.integers(-128, 127))
        cut = data.draw(st.integers(0, stream.size))
        stream = stream[:cut] if data.draw(st.booleans()) else stream
    out = _expand_or_error(stream, cells.size)
    if out is not None and np.array_equal(stream, compress(cells)):
        assert np.array_equal(out, cells)


@pytest.mark.parametrize("start", [1, 3, 7])
def test_unaligned_input_views(start):
    big = np.full(4003, -1, np.int8)
    big[1000:1100] = 0
    big[2000:2003] = 100
    cells = big[start:]
    assert np.array_equal(decompress(compress(cells), cells.size), cells)
    assert compress(cells).tolist() == compress(cells.copy()).tolist()

"""Map deltas (coopd/sharing/delta.py): a delta applied to the map it was made from gives the sender's map
bit for bit (and the same full message), the ledger falls back to the full map when it should, and a
hostile delta is refused without changing anything."""

import zlib

import numpy as np
import pytest

from coopd.grid import OccupancyGrid
from coopd.sharing import delta, wire
from coopd.sharing.delta import (
    DELTA_HEADER,
    BrickLedger,
    DeltaBaseError,
    apply_delta,
    encode_delta,
    peek_delta,
)
from coopd.sharing.wire import MapMeta, WireError

VID = 3


def explore(seed: int, versions: int, edits: int = 40, spread: int = 30):
    """A growing map edited at random, as published: (grid snapshot cropped to the known box, version, full
    message) per version. The box grows (new keys far out) and cells change values of every class."""
    rng = np.random.default_rng(seed)
    grid = OccupancyGrid.empty((20, 20, 10), 0.1)
    out = []
    for v in range(1, versions + 1):
        reach = spread + 4 * v
        keys = rng.integers(-reach, reach, size=(edits, 3))
        keys[:, 2] //= 4
        values = rng.choice(np.array([0, 10, 40, 50, 90, 100, -2, -1], dtype=np.int8), size=edits)
        grid.set_keys(keys, values)
        snap = grid.shrunk(pad=int(rng.integers(0, 5)))
        out.append((snap, v, wire.encode_map(snap, MapMeta(VID, v, 1000.0 + v))))
    return out


def held(message):
    """What a receiver holds after the full message: the decoded grid and meta."""
    return wire.decode_map(message)


@pytest.mark.parametrize("edge", [4, 8, 16])
def test_random_edits_rebuild_the_map_bit_for_bit_from_every_older_base(edge):
    maps = explore(seed=edge, versions=24)
    ledger = BrickLedger(edge, full_share=10.0)  # never fall back: every delta is checked
    for i, (snap, v, message) in enumerate(maps):
        ledger.record(snap, v, message)
        for _, base_v, base_message in maps[max(0, i - 6):i]:
            data = ledger.delta_for(base_v)
            assert data is not None
            base_grid, base_meta = held(base_message)
            before = base_grid.cells.copy()
            grid, meta = apply_delta(base_grid, base_meta, data)
            assert grid.shape == snap.shape and np.array_equal(grid.offset, snap.offset)
            assert np.array_equal(grid.cells, snap.cells)
            assert meta == MapMeta(VID, v, 1000.0 + v)
            assert wire.encode_map(grid, meta) == message  # the receiver stores the sender's full message
            assert np.array_equal(base_grid.cells, before)  # the base is never changed


def test_the_box_may_shrink_and_grow_again():
    """Known cells that vanish (a map re-anchored, cropped) and come back later travel correctly."""
    ledger = BrickLedger(8, full_share=10.0)
    big = OccupancyGrid.empty((60, 60, 10), 0.1)
    big.set_keys([[-25, -25, 0], [25, 25, 2], [0, 0, 0]], np.array([100, 0, 50], dtype=np.int8))
    small = OccupancyGrid.empty((60, 60, 10), 0.1)
    small.set_keys([[0, 0, 0]], np.array([50], dtype=np.int8))
    again = big.copy()
    again.set_keys([[25, 25, 2]], np.array([10], dtype=np.int8))
    history = []
    for v, g in enumerate((big.shrunk(), small.shrunk(), again.shrunk(), small.shrunk(pad=3)), start=1):
        message = wire.encode_map(g, MapMeta(VID, v, 0.0))
        ledger.record(g, v, message)
        for base_v, base_message in history:
            grid, _ = apply_delta(*held(base_message), ledger.delta_for(base_v))
            assert np.array_equal(grid.cells, g.cells) and np.array_equal(grid.offset, g.offset)
        history.append((v, message))


def test_a_2d_map_and_a_map_without_changes():
    ledger = BrickLedger(16, full_share=10.0)
    g = OccupancyGrid(np.full((37, 21, 1), -1, dtype=np.int8), 0.05, (-3, 5, 0))
    g.cells[3:9, 2:4, 0] = 100
    ledger.record(g, 1, m1 := wire.encode_map(g, MapMeta(VID, 1, 0.0)))
    ledger.record(g.copy(), 2, wire.encode_map(g, MapMeta(VID, 2, 0.0)))
    data = ledger.delta_for(1)
    assert peek_delta(data).bricks == 0
    grid, meta = apply_delta(*held(m1), data)
    assert np.array_equal(grid.cells, g.cells) and meta.version == 2


def test_the_ledger_sends_the_full_map_when_it_should():
    maps = explore(seed=1, versions=4)
    ledger = BrickLedger(8)
    assert ledger.delta_for(1) is None  # nothing recorded
    for snap, v, message in maps:
        ledger.record(snap, v, message)
    assert ledger.delta_for(77) is None  # a base it never recorded
    assert ledger.delta_for(4) is None  # the latest itself: nothing to send
    changed = maps[-1][0].copy()
    changed.cells[...] = np.where(changed.cells == -1, 0, 100).astype(np.int8)  # everything changed
    ledger.record(changed, 5, wire.encode_map(changed, MapMeta(VID, 5, 0.0)))
    assert ledger.delta_for(4) is None
    ledger = BrickLedger(8, full_share=10.0)
    for v in range(1, delta.MAX_BASES + 3):
        g = maps[0][0].copy()
        ledger.record(g, v, wire.encode_map(g, MapMeta(VID, v, 0.0)))
    assert ledger.delta_for(1) is None  # too old a base: forgotten
    assert ledger.delta_for(delta.MAX_BASES) is not None


def test_a_small_change_makes_a_small_delta():
    g = OccupancyGrid.empty((200, 200, 30), 0.1)
    rng = np.random.default_rng(5)
    g.cells[20:180, 20:180, 2:25] = rng.choice(np.array([0, 100, 30], dtype=np.int8), size=(160, 160, 23))
    ledger = BrickLedger()
    m1 = wire.encode_map(g, MapMeta(VID, 1, 0.0))
    ledger.record(g, 1, m1)
    g2 = g.copy()
    g2.cells[100:104, 100:104, 10] = 70
    ledger.record(g2, 2, wire.encode_map(g2, MapMeta(VID, 2, 0.0)))
    data = ledger.delta_for(1)
    assert peek_delta(data).bricks == 1
    assert len(data) * 50 < len(m1)


def test_record_refuses_a_message_that_is_not_the_grid():
    g = OccupancyGrid.empty((20, 20, 10), 0.1)
    ledger = BrickLedger()
    with pytest.raises(ValueError):
        ledger.record(g, 2, wire.encode_map(g, MapMeta(VID, 1, 0.0)))
    with pytest.raises(ValueError):
        ledger.record(g.shrunk(pad=1), 1, wire.encode_map(g, MapMeta(VID, 1, 0.0)))
    ledger.record(g, 2, wire.encode_map(g, MapMeta(VID, 2, 0.0)))
    with pytest.raises(ValueError):
        ledger.record(g, 2, wire.encode_map(g, MapMeta(VID, 2, 0.0)))


# ------------------------------------------------------------------------------------ hostile deltas
def two_versions():
    a = OccupancyGrid.empty((40, 40, 10), 0.1)
    a.cells[5:30, 5:30, 2:8] = 0
    b = a.copy()
    b.cells[10:12, 10:12, 3] = 100
    b.cells[33, 33, 1] = 50
    ma, mb = wire.encode_map(a, MapMeta(VID, 1, 0.0)), wire.encode_map(b, MapMeta(VID, 2, 0.0))
    ledger = BrickLedger(8, full_share=10.0)
    ledger.record(a, 1, ma)
    ledger.record(b, 2, mb)
    return held(ma), b, ledger.delta_for(1)


def forged(grid, linear, stream, count=None, index=None, **fields) -> bytes:
    """A delta of `grid`'s header carrying brick indices `linear` and cells `stream` as given (raw cells),
    with any header field replaced; CRCs made right unless given."""
    import zstandard

    gaps = np.diff(np.asarray(linear, dtype=np.int64), prepend=0).astype("<u4")
    if index is None:
        index = zstandard.ZstdCompressor(write_content_size=True).compress(gaps.tobytes())
    payload = index + np.asarray(stream, dtype=np.int8).tobytes()
    f = dict(type=delta.MSG_MAP_DELTA, fmt=1, hlen=DELTA_HEADER.size, vid=VID, map_type=1, map_enc=3,
             brick_enc=0, edge=8, shape=grid.shape, offset=tuple(int(v) for v in grid.offset),
             res=grid.resolution, stamp=0.0, base=1, version=2, count=len(linear) if count is None else count,
             crc_cells=delta.cells_crc32(grid), index_size=len(index), payload_size=len(payload),
             crc_payload=zlib.crc32(payload))
    f.update(fields)
    header = DELTA_HEADER.pack(f["type"], f["fmt"], f["hlen"], f["vid"], f["map_type"], f["map_enc"],
                               f["brick_enc"], f["edge"], *f["shape"], *f["offset"], f["res"], f["stamp"],
                               f["base"], f["version"], f["count"], f["crc_cells"], f["index_size"],
                               f["payload_size"], f["crc_payload"])
    return header + payload


def test_a_forged_delta_built_right_applies():
    """The forging helper is right: each hostile variant below differs from a valid delta in one thing."""
    (base, meta), target, _ = two_versions()
    lat_lo, lat_n = delta.lattice_of(target.offset, target.shape, 8)
    bricks = np.argwhere(np.ones(tuple(lat_n), dtype=bool))
    linear = np.ravel_multi_index(bricks.T, tuple(lat_n))
    boxes = delta.k.brick_boxes(bricks + lat_lo, 8, target.offset, np.array(target.shape))
    stream = np.empty(target.size, dtype=np.int8)
    delta.k.copy_boxes(target.cells, boxes, stream, True)
    grid, _ = apply_delta(base, meta, forged(target, linear, stream))
    assert np.array_equal(grid.cells, target.cells)


def brick_cells(target, linear) -> int:
    """Cells of the bricks `linear` (lattice indices, edge 8) inside the target's box."""
    lat_lo, lat_n = delta.lattice_of(target.offset, target.shape, 8)
    bricks = np.stack(np.unravel_index(np.asarray(linear), tuple(lat_n)), axis=1) + lat_lo
    boxes = delta.k.brick_boxes(bricks.astype(np.int64), 8, target.offset, np.array(target.shape))
    return int(np.prod(boxes[:, 3:] - boxes[:, :3], axis=1).sum())


def hostile_cases(target):
    lat_n = delta.lattice_of(target.offset, target.shape, 8)[1]
    lattice = int(np.prod(lat_n))
    n = brick_cells(target, [1])
    brick = np.zeros(n, dtype=np.int8)
    two = np.zeros(brick_cells(target, [1, 2]), dtype=np.int8)
    return {
        "brick out of the lattice": (forged(target, [lattice], brick), WireError),
        "duplicate brick": (forged(target, [1, 1], two), WireError),
        "bricks out of order": (forged(target, [2, 1], two), WireError),
        "count above the lattice": (forged(target, [1], brick, count=lattice + 1), WireError),
        "count disagrees with the index": (forged(target, [1, 2], two, count=1), WireError),
        "too few cells": (forged(target, [1, 2], brick), WireError),
        "too many cells": (forged(target, [1], np.zeros(n + 1, dtype=np.int8)), WireError),
        "cell value out of range": (forged(target, [1], np.full(n, 101, dtype=np.int8)), WireError),
        "index frame bomb": (forged(target, [1], brick, index=b"\x28\xb5\x2f\xfd" + bytes(20)), WireError),
        "payload corrupted": (forged(target, [1], brick, crc_payload=1), WireError),
        "wrong base version": (forged(target, [1], brick, base=7, version=9), DeltaBaseError),
        "another vehicle": (forged(target, [1], brick, vid=VID + 1), DeltaBaseError),
        "not the sender's cells": (forged(target, [1], np.full(n, 100, dtype=np.int8)), DeltaBaseError),
        "backwards versions": (forged(target, [1], brick, base=2, version=1), WireError),
        "brick edge 7": (forged(target, [1], brick, edge=7), WireError),
        "unknown encoding": (forged(target, [1], brick, brick_enc=9), WireError),
        "newer format": (forged(target, [1], brick, fmt=2), wire.MessageVersionError),
        "short header length": (forged(target, [1], brick, hlen=40), WireError),
        "huge map": (forged(target, [1], brick, shape=(100000, 100000, 100)), WireError),
        "largest box": (forged(target, [1], brick, shape=(2**31 - 1,) * 3, count=2**32 - 1), WireError),
        "other resolution": (forged(target, [1], brick, res=0.2), DeltaBaseError),
        "nan stamp": (forged(target, [1], brick, stamp=float("nan")), WireError),
    }


@pytest.mark.parametrize("case", list(hostile_cases(two_versions()[1])))
def test_a_hostile_delta_is_refused_and_changes_nothing(case):
    (base, meta), target, _ = two_versions()
    data, error = hostile_cases(target)[case]
    before = base.cells.copy()
    with pytest.raises(error):
        apply_delta(base, meta, data)
    assert np.array_equal(base.cells, before)


def test_a_truncated_or_padded_delta_is_refused():
    (base, meta), _, data = two_versions()
    apply_delta(base, meta, data)
    for cut in (1, 3, 40, len(data) - 1):
        with pytest.raises(WireError):
            apply_delta(base, meta, data[:cut])
    with pytest.raises(WireError):
        apply_delta(base, meta, data + b"\0")
    with pytest.raises(WireError):
        apply_delta(base, meta, data, wire.DecodeLimits(max_cells=1000))
    with pytest.raises(WireError):
        apply_delta(base, meta, data, wire.DecodeLimits(max_bytes=len(data) - 1))


def test_encode_delta_refuses_what_a_reader_would_refuse():
    g = OccupancyGrid.empty((20, 20, 10), 0.1)
    with pytest.raises(ValueError):
        encode_delta(g, MapMeta(VID, 2, 0.0), 1, np.zeros((0, 3)), edge=12)
    with pytest.raises(ValueError):
        encode_delta(g, MapMeta(VID, 2, 0.0), 1, np.zeros((0, 3)), brick_encoding="gzip")

"""Map deltas (wire type 4): only the bricks of cells that changed since a version the receiver holds.

A map is cut into bricks of B×B×B cells aligned on absolute cell keys (brick b holds keys b·B ..
b·B + B − 1 on each axis), so a brick is the same region whatever box the map covers as it grows.
The sender's `BrickLedger` keeps a hash and a version per brick: every published map is hashed
brick by brick (its known cells, positions and values) and the bricks whose hash changed get the
new version. A peer holding version v then needs the bricks changed after v; `encode_delta` writes
them with the new map's box and header, `apply_delta` rebuilds the new map from the map at v and
those bricks: cells inside both boxes come from v, cells outside v's box are unknown, every sent
brick overwrites its cells. The delta carries the CRC-32 of the new map's cells, so the rebuilt map
is checked to be the sender's bit for bit (a base that differs, or a brick hash that collided, is
refused and the full map sent instead).

Everything here is pure (no sockets): MTP (coopd/sharing/service.py) or any other transport sends the
bytes. Layout and rules in docs/protocol.md §3.4. Every input is hostile: sizes and counts are
checked before anything is allocated, the brick index must be strictly increasing inside the new
map's brick lattice, and nothing of a refused delta is kept.
"""

import math
import struct
import threading
import zlib
from dataclasses import dataclass

import numpy as np

from coopd.grid import OccupancyGrid
from coopd.grid.cells import CELL_DTYPE, UNKNOWN

from . import delta_kernels as k
from . import wire
from .wire import DecodeLimits, MapMeta, WireError
from .wire_options import BRICK_EDGES, DEFAULT_BRICK_EDGE, MSG_MAP_DELTA

DELTA_FORMAT_VERSION = 1
DELTA_HEADER = struct.Struct("<bBHiBBBB3i3iddQQIIIII")
"""type, format version, header length, vehicle id, map type, map encoding, brick encoding, brick
edge, m_x m_y m_z, offset (key of array cell 0, 0, 0), resolution, stamp, base version, map version,
brick count, CRC-32 of the new map's cells, index frame size, payload size, CRC-32 of the payload."""
FULL_SHARE = 0.5
"""A delta larger than this share of the full map message is not sent: the full map is."""
MAX_BASES = 256
"""Versions a BrickLedger can make deltas from (the newest ones); older bases get the full map."""
INDEX_ITEM = np.dtype("<u4")


class DeltaBaseError(WireError):
    """The receiver does not hold the map the delta applies to, or the rebuilt map is not the sender's:
    the sender must send the full map."""


@dataclass(frozen=True)
class DeltaInfo(wire.SizedHeader):
    """A delta's header, validated, without touching the payload (see peek_delta)."""

    vehicle_id: int
    shape: tuple[int, int, int]
    offset: tuple[int, int, int]
    resolution: float
    stamp: float
    base_version: int
    map_version: int
    map_encoding: str
    brick_encoding: str
    brick_edge: int
    bricks: int
    cells_crc32: int
    index_size: int
    header_size: int
    payload_size: int
    payload_crc32: int

    def lattice(self) -> tuple[np.ndarray, np.ndarray]:
        """(lowest brick, bricks per axis) of the brick lattice covering the new map's box."""
        return lattice_of(np.array(self.offset, dtype=np.int64), self.shape, self.brick_edge)


def lattice_of(offset, shape, edge: int) -> tuple[np.ndarray, np.ndarray]:
    """(lowest brick coordinates, bricks per axis) of the bricks the key box offset..offset+shape-1 meets."""
    lo = np.floor_divide(np.asarray(offset, dtype=np.int64), edge)
    hi = np.floor_divide(np.asarray(offset, dtype=np.int64) + np.asarray(shape, dtype=np.int64) - 1, edge)
    return lo, hi - lo + 1


def cells_crc32(grid: OccupancyGrid) -> int:
    """CRC-32 of a grid's cells in row-major order (what a delta promises the rebuilt map holds)."""
    return zlib.crc32(grid.flat)


# --------------------------------------------------------------------------------------- encode
def encode_delta(grid: OccupancyGrid, meta: MapMeta, base_version: int, bricks: np.ndarray,
                 edge: int = DEFAULT_BRICK_EDGE, map_encoding: str = "default",
                 brick_encoding: str = "default") -> bytes:
    """A delta message (type 4) turning the map at `base_version` into `grid` at `meta.version`,
    carrying the cells of `bricks` ((K, 3) brick coordinates; those outside the grid's lattice are
    left out). map_encoding: how the receiver encodes the rebuilt map (as the sender's full message)."""
    map_encoding = wire.DEFAULT_ENCODING if map_encoding == "default" else map_encoding
    brick_encoding = wire.DEFAULT_ENCODING if brick_encoding == "default" else brick_encoding
    for name in (map_encoding, brick_encoding):
        if name not in wire.ENCODINGS:
            raise ValueError(f"unknown encoding {name!r}")
    if edge not in BRICK_EDGES:
        raise ValueError(f"brick edge {edge} is not one of {BRICK_EDGES}")
    if not (0 <= int(base_version) < 2**64 and 0 <= int(meta.version) < 2**64 and math.isfinite(meta.stamp)):
        raise ValueError(f"versions must be 0..2**64-1 and the stamp finite: {base_version}, {meta}")
    offset = grid.offset
    lat_lo, lat_n = lattice_of(offset, grid.shape, edge)
    rel = np.asarray(bricks, dtype=np.int64).reshape(-1, 3) - lat_lo
    inside = np.all((rel >= 0) & (rel < lat_n), axis=1)
    linear = np.unique((rel[inside, 0] * lat_n[1] + rel[inside, 1]) * lat_n[2] + rel[inside, 2])
    order = np.stack(np.unravel_index(linear, tuple(lat_n)), axis=1).astype(np.int64) + lat_lo
    boxes = k.brick_boxes(order, edge, offset, np.array(grid.shape, dtype=np.int64))
    n = int(np.prod(boxes[:, 3:] - boxes[:, :3], axis=1).sum()) if len(boxes) else 0
    stream = np.empty(n, dtype=CELL_DTYPE)
    k.copy_boxes(grid.cells, boxes, stream, True)
    gaps = np.diff(linear, prepend=0).astype(INDEX_ITEM)
    import zstandard

    index = zstandard.ZstdCompressor(level=3, write_content_size=True).compress(gaps.tobytes())
    payload = index + wire.encode_payload(stream, brick_encoding)
    if len(payload) > 2**32 - 1:
        raise ValueError("delta payload exceeds 4 GiB")
    map_type = wire.MAP_2D if grid.shape[2] == 1 else wire.MAP_3D
    header = DELTA_HEADER.pack(
        MSG_MAP_DELTA, DELTA_FORMAT_VERSION, DELTA_HEADER.size, int(meta.vehicle_id), map_type,
        wire.ENCODINGS[map_encoding], wire.ENCODINGS[brick_encoding], edge, *grid.shape,
        *(int(v) for v in offset), grid.resolution, float(meta.stamp), int(base_version), int(meta.version),
        len(linear), cells_crc32(grid), len(index), len(payload), zlib.crc32(payload))
    return header + payload


# --------------------------------------------------------------------------------------- decode
def peek_delta(data) -> DeltaInfo:
    """The header of a delta message, validated, without decoding the payload."""
    data = memoryview(data)
    if len(data) < 4:
        raise WireError(f"a delta header needs 4 bytes, got {len(data)}")
    msg_type, fmt, header_len = wire.COOPD_PREFIX.unpack_from(data)
    if msg_type != MSG_MAP_DELTA:
        raise wire.UnknownMessageType(f"message type {msg_type} is not a map delta")
    if fmt > DELTA_FORMAT_VERSION:
        raise wire.MessageVersionError(f"map delta format version {fmt} is newer than this coopd reads "
                                       f"(<= {DELTA_FORMAT_VERSION})")
    if fmt < 1:
        raise WireError(f"map delta format version {fmt} does not exist")
    if header_len < DELTA_HEADER.size:
        raise WireError(f"delta header length {header_len} is shorter than the {DELTA_HEADER.size} bytes "
                        f"of format version {fmt}")
    if len(data) < header_len:
        raise WireError(f"the delta header needs {header_len} bytes, got {len(data)}")
    (_, _, _, vid, map_type, map_enc, brick_enc, edge, mx, my, mz, ox, oy, oz, res, stamp, base, version,
     count, crc_cells, index_size, payload_size, crc_payload) = DELTA_HEADER.unpack_from(data)
    shape = wire._check_shape((mx, my, mz), map_type)
    for enc in (map_enc, brick_enc):
        if enc not in wire.ENCODING_NAMES:
            raise WireError(f"unknown encoding id {enc}")
    if edge not in BRICK_EDGES:
        raise WireError(f"brick edge {edge} is not one of {BRICK_EDGES}")
    if not (math.isfinite(res) and 1e-4 <= res <= 100.0):
        raise WireError(f"resolution {res} m is outside 1e-4..100 m")
    if not math.isfinite(stamp):
        raise WireError(f"timestamp {stamp} is not finite")
    if version <= base:
        raise WireError(f"delta from version {base} to {version} does not go forward")
    _, lat_n = lattice_of(np.array((ox, oy, oz), dtype=np.int64), shape, edge)
    lattice = math.prod(int(v) for v in lat_n)  # Python ints: a hostile box cannot overflow it
    if count > lattice:
        raise WireError(f"{count} bricks, but the map's lattice holds {lattice}")
    if index_size > payload_size:
        raise WireError(f"brick index of {index_size} bytes is larger than the payload ({payload_size})")
    return DeltaInfo(vid, shape, (ox, oy, oz), res, stamp, base, version, wire.ENCODING_NAMES[map_enc],
                     wire.ENCODING_NAMES[brick_enc], edge, count, crc_cells, index_size, header_len,
                     payload_size, crc_payload)


def _brick_index(frame, count: int, lattice_cells: int) -> np.ndarray:
    """The K linear lattice indices of the index frame: strictly increasing, inside the lattice."""
    cells = wire._unzstd(frame, cap=count * INDEX_ITEM.itemsize)
    if len(cells) != count * INDEX_ITEM.itemsize:
        raise WireError(f"brick index holds {len(cells)} bytes for {count} bricks")
    gaps = np.frombuffer(cells.tobytes(), dtype=INDEX_ITEM).astype(np.int64)
    if count and np.any(gaps[1:] == 0):
        raise WireError("brick index names a brick twice")
    linear = np.cumsum(gaps)
    if count and linear[-1] >= lattice_cells:
        raise WireError(f"brick index {int(linear[-1])} is outside the lattice of {lattice_cells} bricks")
    return linear


def apply_delta(base: OccupancyGrid, base_meta: MapMeta, data,
                limits: DecodeLimits = wire.DEFAULT_LIMITS) -> tuple[OccupancyGrid, MapMeta]:
    """The map a delta describes, rebuilt from the map it applies to (`base` is not changed).
    WireError if the delta is malformed; DeltaBaseError if `base` is not the map it applies to or
    the rebuilt map's cells are not the sender's."""
    if len(data) > limits.max_bytes:
        raise WireError(f"delta of {len(data)} bytes exceeds the limit of {limits.max_bytes}")
    info = peek_delta(data)
    if info.cells > limits.max_cells:
        raise WireError(f"map of {info.shape} = {info.cells} cells exceeds the limit of {limits.max_cells}")
    if len(data) != info.total_size:
        raise WireError(f"delta is {len(data)} bytes but its header announces {info.total_size}")
    if base_meta.vehicle_id != info.vehicle_id or base_meta.version != info.base_version:
        raise DeltaBaseError(f"delta of vehicle {info.vehicle_id} applies to v{info.base_version}; the map "
                             f"held is vehicle {base_meta.vehicle_id} v{base_meta.version}")
    if abs(base.resolution - info.resolution) > 1e-9 * info.resolution:
        raise DeltaBaseError(f"delta at {info.resolution} m for a map at {base.resolution} m")
    payload = memoryview(data)[info.header_size:]
    if zlib.crc32(payload) != info.payload_crc32:
        raise WireError("delta payload CRC-32 mismatch: the message is corrupted")
    lat_lo, lat_n = info.lattice()
    linear = _brick_index(payload[:info.index_size], info.bricks, int(np.prod(lat_n)))
    bricks = np.stack(np.unravel_index(linear, tuple(lat_n)), axis=1).astype(np.int64) + lat_lo
    offset = np.array(info.offset, dtype=np.int64)
    boxes = k.brick_boxes(bricks, info.brick_edge, offset, np.array(info.shape, dtype=np.int64))
    n = int(np.prod(boxes[:, 3:] - boxes[:, :3], axis=1).sum()) if len(boxes) else 0
    stream = wire.decode_payload(payload[info.index_size:], info.brick_encoding, n)
    grid = OccupancyGrid(np.full(info.shape, UNKNOWN, dtype=CELL_DTYPE), info.resolution, offset)
    grid.paste(base)
    k.copy_boxes(grid.cells, boxes, stream, False)
    if cells_crc32(grid) != info.cells_crc32:
        raise DeltaBaseError(f"the map rebuilt from v{info.base_version} differs from the sender's "
                             f"v{info.map_version} (CRC-32 of the cells)")
    return grid, MapMeta(info.vehicle_id, info.map_version, info.stamp)


# --------------------------------------------------------------------------------------- sender state
class BrickLedger:
    """The sender's record of which bricks of its map changed at which published version, and the
    latest map itself: `record` every published map, `delta_for` a version a peer holds.

    It keeps a hash and a sequence number per brick over the union of the lattices of every map
    recorded (a brick outside the current map is all unknown), the latest grid and full message, and
    the sequence number of each of the last MAX_BASES versions. Thread-safe: the publisher records,
    the senders ask."""

    def __init__(self, edge: int = DEFAULT_BRICK_EDGE, full_share: float = FULL_SHARE):
        if edge not in BRICK_EDGES:
            raise ValueError(f"brick edge {edge} is not one of {BRICK_EDGES}")
        self.edge, self.full_share = edge, full_share
        self._lock = threading.Lock()
        self._lo = np.zeros(3, dtype=np.int64)
        self._hashes = np.zeros((0, 0, 0), dtype=np.uint64)
        self._seqs = np.zeros((0, 0, 0), dtype=np.int64)
        self._seq = 0
        self._bases: dict[int, int] = {}
        """version -> sequence number, for the last MAX_BASES versions recorded."""
        self._latest: tuple[int, OccupancyGrid, MapMeta, str, int] | None = None
        """version, grid, meta, encoding and size of the full message of the latest map."""
        self._deltas: dict[int, bytes | None] = {}
        """base version -> delta to the latest (None: the full map is smaller), made when first asked."""

    @property
    def latest_version(self) -> int | None:
        latest = self._latest
        return None if latest is None else latest[0]

    @property
    def held_bytes(self) -> int:
        """Memory this ledger holds: the latest map's cells and 16 bytes per brick of the union lattice."""
        latest = self._latest
        return (0 if latest is None else latest[1].size) + 16 * self._hashes.size

    def record(self, grid: OccupancyGrid, version: int, message: bytes) -> int:
        """Note the map published as `version` (its full message `message`, which must carry `grid`);
        returns the number of bricks that changed since the previous one. The grid is kept, not copied:
        the caller must not change it afterwards."""
        info = wire.peek(message)
        offset = tuple(int(v) for v in grid.offset)
        if info.message_type != wire.MSG_COOPD_MAP or info.map_version != version \
                or tuple(info.shape) != tuple(grid.shape) or tuple(info.offset) != offset:
            raise ValueError(f"message (v{info.map_version}, {info.shape} at {info.offset}) is not the map "
                             f"recorded (v{version}, {grid.shape} at {tuple(grid.offset)})")
        meta = MapMeta(info.vehicle_id, version, info.stamp)
        lat_lo, lat_n = lattice_of(grid.offset, grid.shape, self.edge)
        hashes = np.empty(tuple(int(v) for v in lat_n), dtype=np.uint64)
        k.brick_hashes(grid.cells, grid.offset, lat_lo, self.edge, hashes)
        with self._lock:
            if self._latest is not None and version <= self._latest[0]:
                raise ValueError(f"version {version} is not newer than the recorded {self._latest[0]}")
            self._grow_to(lat_lo, lat_n)
            old_h, old_s = self._window(lat_lo, lat_n)
            outside = np.ones(self._hashes.shape, dtype=bool)  # bricks of the union beyond this map
            sl = self._slices(lat_lo, lat_n)
            outside[sl] = False
            self._seq += 1
            changed = hashes != old_h
            old_s[changed] = self._seq
            old_h[...] = hashes
            gone = outside & (self._hashes != k.EMPTY_HASH)  # known before, outside the map now
            self._seqs[gone] = self._seq
            self._hashes[gone] = k.EMPTY_HASH
            self._bases[version] = self._seq
            while len(self._bases) > MAX_BASES:
                del self._bases[next(iter(self._bases))]
            self._latest = (version, grid, meta, info.encoding, len(message))
            self._deltas = {}
            return int(changed.sum() + gone.sum())

    def delta_for(self, base_version: int) -> bytes | None:
        """The delta from `base_version` to the latest map, or None when the full map is to be sent:
        no map recorded, a base this ledger does not know (never recorded, too old, or not older than
        the latest), or a delta larger than full_share of the full message."""
        with self._lock:
            latest = self._latest
            if latest is None or base_version not in self._bases or base_version >= latest[0]:
                return None
            if base_version in self._deltas:
                return self._deltas[base_version]
            base_seq = self._bases[base_version]
            version, grid, meta, encoding, full_size = latest
            lat_lo, lat_n = lattice_of(grid.offset, grid.shape, self.edge)
            _, seqs = self._window(lat_lo, lat_n)
            bricks = np.argwhere(seqs > base_seq) + lat_lo
            budget = self.full_share * full_size
            delta = None
            if len(bricks) < seqs.size or self.full_share > 1:  # every brick changed: no need to try
                message = encode_delta(grid, meta, base_version, bricks, self.edge, encoding, encoding)
                delta = message if len(message) <= budget else None
            self._deltas[base_version] = delta
            return delta

    # ------------------------------------------------------------------ union lattice
    def _slices(self, lat_lo, lat_n) -> tuple[slice, ...]:
        start = lat_lo - self._lo
        return tuple(slice(int(s), int(s + n)) for s, n in zip(start, lat_n, strict=True))

    def _window(self, lat_lo, lat_n) -> tuple[np.ndarray, np.ndarray]:
        sl = self._slices(lat_lo, lat_n)
        return self._hashes[sl], self._seqs[sl]

    def _grow_to(self, lat_lo, lat_n) -> None:
        """Extend the union lattice to hold lat_lo .. lat_lo + lat_n - 1 (new bricks: never known, seq 0)."""
        if self._hashes.size == 0:
            self._lo = lat_lo.copy()
            self._hashes = np.full(tuple(int(v) for v in lat_n), k.EMPTY_HASH, dtype=np.uint64)
            self._seqs = np.zeros(self._hashes.shape, dtype=np.int64)
            return
        lo = np.minimum(self._lo, lat_lo)
        hi = np.maximum(self._lo + np.array(self._hashes.shape), lat_lo + lat_n)
        if np.array_equal(lo, self._lo) and np.array_equal(hi, self._lo + np.array(self._hashes.shape)):
            return
        shape = tuple(int(v) for v in hi - lo)
        hashes = np.full(shape, k.EMPTY_HASH, dtype=np.uint64)
        seqs = np.zeros(shape, dtype=np.int64)
        start = self._lo - lo
        sl = tuple(slice(int(s), int(s + n)) for s, n in zip(start, self._hashes.shape, strict=True))
        hashes[sl] = self._hashes
        seqs[sl] = self._seqs
        self._lo, self._hashes, self._seqs = lo, hashes, seqs

"""Map messages on the wire and on disk (thesis §7.2, notes §5; byte tables in docs/protocol.md).

Two message types carry a map:
- type 0, the thesis message: the 27-byte header of Figure 31, byte-exact, read and written;
- type 1, coopd's map message: adds the origin (cells and metres), a map version counter,
  a timestamp, a float64 resolution, an encoding id and a CRC-32; it is versioned, and a
  message newer than this code reads is refused with MessageVersionError.
Type 2 carries merge results (transforms between map frames, distributed merging): see
encode_merge_result / decode_merge_result.
Every input is hostile: sizes are checked against DecodeLimits before anything is allocated.
"""

import math
import struct
import zlib
from dataclasses import dataclass

import numpy as np

from coopd.grid import OccupancyGrid

from . import codec, planes
from .codec import CodecError
from .wire_options import (  # defined there without numpy; callers may import them from here
    DEFAULT_ENCODING,
    DEFAULT_LIMITS,
    ENCODING_NAMES,
    ENCODING_PREFERENCE,
    ENCODINGS,
    MSG_MAP_DELTA,
    DecodeLimits,
)

MSG_THESIS_MAP = 0
MSG_COOPD_MAP = 1
MSG_MERGE_RESULT = 2
"""Merge results: validated transforms between vehicles' map frames (distributed merging)."""
MSG_PEER_HELLO = 3
"""Reserved number for a peer hello / capability exchange (supported encodings); coopd sends none
and refuses one with UnknownMessageType, so that a future use cannot be misread by this version."""
MTP_MARKER = -128
"""Byte 0 of every MTP control frame; never a message type."""

MAP_2D = 0
MAP_3D = 1

COOPD_MAP_VERSION = 1
"""Highest coopd map message format version this code reads and the one it writes."""

THESIS_HEADER = struct.Struct("<bibiiifbi")
COOPD_HEADER = struct.Struct("<bBHiBBH3i3id3dQdII")
COOPD_PREFIX = struct.Struct("<bBH")
"""Bytes every coopd message version starts with: type, format version, header length."""

ZSTD_LEVEL = 3

INT32_MAX = 2**31 - 1


class WireError(ValueError):
    """A malformed, inconsistent or oversized map message."""


class MessageVersionError(WireError):
    """A message format version newer than this coopd can read."""


class UnknownMessageType(WireError):
    """A message type this coopd does not know, or a reserved number it refuses."""


@dataclass(frozen=True)
class MapMeta:
    """What travels with a map besides its cells."""

    vehicle_id: int
    version: int = 0
    """Map version counter: increases whenever the sender's map changed."""
    stamp: float = 0.0
    """Seconds (Unix time) when this version of the map was made."""


class SizedHeader:
    """What a map message's header (full map or delta) says about size: cells of its box (shape) and
    bytes of the whole message (header_size + payload_size)."""

    shape: tuple[int, int, int]
    header_size: int
    payload_size: int

    @property
    def cells(self) -> int:
        return self.shape[0] * self.shape[1] * self.shape[2]

    @property
    def total_size(self) -> int:
        """Bytes of the whole message: where it ends inside a padded MTP transfer."""
        return self.header_size + self.payload_size


@dataclass(frozen=True)
class MessageInfo(SizedHeader):
    """A message's header, read without touching the payload (see peek())."""

    message_type: int
    format_version: int
    vehicle_id: int
    shape: tuple[int, int, int]
    resolution: float
    encoding: str
    header_size: int
    payload_size: int
    offset: tuple[int, int, int] = (0, 0, 0)
    map_version: int = 0
    stamp: float = 0.0
    crc32: int | None = None

    def check(self, limits: "DecodeLimits") -> None:
        """WireError if the announced map or message exceeds limits (lets a transport refuse early)."""
        if self.cells > limits.max_cells:
            raise WireError(f"map of {self.shape} = {self.cells} cells exceeds the limit of "
                            f"{limits.max_cells}")
        if self.total_size > limits.max_bytes:
            raise WireError(f"message of {self.total_size} bytes exceeds the limit of {limits.max_bytes}")


# --------------------------------------------------------------------------------------- encode
def negotiate(peer_encodings) -> str:
    """The encoding to send to a peer that reads `peer_encodings` (names); falls back to thesis."""
    peer = set(peer_encodings)
    for name in ENCODING_PREFERENCE:
        if name in peer:
            return name
    return "thesis"


def _raw_cells(cells: np.ndarray) -> bytes:
    """Flat int8 cells as bytes, refusing values a decoder would refuse."""
    if cells.dtype != np.int8:
        raise ValueError(f"cells must be int8, got {cells.dtype}")
    if cells.size and (cells.min() < codec.CELL_MIN or cells.max() > codec.CELL_MAX):
        raise ValueError(f"cells hold values outside the cell range {codec.CELL_MIN}..{codec.CELL_MAX}")
    return cells.tobytes()


def encode_payload(cells: np.ndarray, encoding: str) -> bytes:
    """The payload of flat int8 cells in a named encoding (no header)."""
    if encoding == "raw":
        return _raw_cells(cells)
    if encoding == "planes-zstd":
        return planes.encode(cells)
    stream = codec.compress(cells)
    if encoding == "thesis":
        return stream.tobytes()
    if encoding == "thesis-zstd":
        import zstandard

        return zstandard.ZstdCompressor(level=ZSTD_LEVEL, write_content_size=True).compress(stream.tobytes())
    raise ValueError(f"unknown encoding {encoding!r}; known: {', '.join(ENCODINGS)}")


def _check_int32(name: str, values) -> None:
    for v in values:
        if not -(2**31) <= int(v) <= INT32_MAX:
            raise ValueError(f"{name} {int(v)} does not fit in int32")


def encode_map(grid: OccupancyGrid, meta: MapMeta, encoding: str = "default") -> bytes:
    """A coopd map message (type 1) carrying the whole grid."""
    encoding = DEFAULT_ENCODING if encoding == "default" else encoding
    if encoding not in ENCODINGS:
        raise ValueError(f"unknown encoding {encoding!r}; known: default, {', '.join(ENCODINGS)}")
    _check_int32("vehicle id", [meta.vehicle_id])
    _check_int32("offset", grid.offset)
    _check_int32("size", grid.shape)
    if not (0 <= int(meta.version) < 2**64 and math.isfinite(meta.stamp)):
        raise ValueError(f"map version must be 0..2**64-1 and stamp finite, got {meta}")
    payload = encode_payload(grid.flat, encoding)
    if len(payload) > 2**32 - 1:
        raise ValueError("payload exceeds 4 GiB")
    offset = [int(v) for v in grid.offset]
    map_type = MAP_2D if grid.shape[2] == 1 else MAP_3D
    header = COOPD_HEADER.pack(
        MSG_COOPD_MAP, COOPD_MAP_VERSION, COOPD_HEADER.size, int(meta.vehicle_id), map_type,
        ENCODINGS[encoding], 0, *grid.shape, *offset, grid.resolution,
        *(o * grid.resolution for o in offset), int(meta.version), float(meta.stamp),
        len(payload), zlib.crc32(payload))
    return header + payload


VERSION_OFFSET = 68
"""Byte offset of the map version in a coopd map message (type 1); the CRC covers the payload only."""


def with_version(message, version: int) -> bytes:
    """A copy of a coopd map message (type 1) carrying another map version."""
    info = peek(message)
    if info.message_type != MSG_COOPD_MAP:
        raise WireError(f"message type {info.message_type} carries no map version")
    if not 0 <= int(version) < 2**64:
        raise ValueError(f"map version must be 0..2**64-1, got {version}")
    out = bytearray(message)
    struct.pack_into("<Q", out, VERSION_OFFSET, int(version))
    return bytes(out)


def encode_thesis_map(grid: OccupancyGrid, vehicle_id: int, compressed: bool = True) -> bytes:
    """A thesis message (type 0, Figure 31), byte-exact; it cannot carry the origin or version."""
    _check_int32("vehicle id", [vehicle_id])
    payload = codec.compress(grid.flat).tobytes() if compressed else _raw_cells(grid.flat)
    if len(payload) > INT32_MAX:
        raise ValueError("payload exceeds the int32 data size of the thesis header")
    map_type = MAP_2D if grid.shape[2] == 1 else MAP_3D
    header = THESIS_HEADER.pack(MSG_THESIS_MAP, int(vehicle_id), map_type, *grid.shape,
                                grid.resolution, 1 if compressed else 0, len(payload))
    return header + payload


# --------------------------------------------------------------------------------------- decode
def _need(data, n: int, what: str) -> None:
    if len(data) < n:
        raise WireError(f"{what} needs {n} bytes, got {len(data)}")


def _check_shape(shape, map_type: int) -> tuple[int, int, int]:
    if min(shape) < 1:
        raise WireError(f"map size {shape} has a non-positive dimension")
    if map_type not in (MAP_2D, MAP_3D):
        raise WireError(f"map type {map_type} is neither 0 (2D) nor 1 (3D)")
    if map_type == MAP_2D and shape[2] != 1:
        raise WireError(f"2D map with m_z = {shape[2]} (must be 1)")
    return tuple(int(s) for s in shape)


def _float32_resolution(value: float) -> float:
    """The decimal a float32 resolution was written from (0.1f reads back as 0.1)."""
    return float(str(np.float32(value)))


def peek(data) -> MessageInfo:
    """The header of a map message, validated, without decoding the payload."""
    data = memoryview(data)
    _need(data, 1, "a message")
    msg_type = struct.unpack_from("<b", data)[0]
    if msg_type == MSG_THESIS_MAP:
        return _peek_thesis(data)
    if msg_type == MSG_COOPD_MAP:
        return _peek_coopd(data)
    if msg_type == MTP_MARKER:
        raise UnknownMessageType("byte 0 is -128, an MTP control frame, not a message")
    if msg_type == MSG_MERGE_RESULT:
        raise UnknownMessageType("message type 2 is a merge result, not a map (decode_merge_result)")
    if msg_type == MSG_MAP_DELTA:
        raise UnknownMessageType("message type 4 is a map delta, not a whole map (delta.apply_delta)")
    if msg_type == MSG_PEER_HELLO:
        raise UnknownMessageType(f"message type {msg_type} is reserved: this coopd refuses it")
    raise UnknownMessageType(f"unknown message type {msg_type}")


def _peek_thesis(data) -> MessageInfo:
    _need(data, THESIS_HEADER.size, "a thesis map header")
    _, vid, map_type, mx, my, mz, res, compressed, size = THESIS_HEADER.unpack_from(data)
    shape = _check_shape((mx, my, mz), map_type)
    if compressed not in (0, 1):
        raise WireError(f"is-compressed flag is {compressed}, not 0 or 1")
    if size < 0:
        raise WireError(f"data size {size} is negative")
    if not (math.isfinite(res) and res > 0):
        raise WireError(f"resolution {res} is not a positive number")
    return MessageInfo(MSG_THESIS_MAP, 0, vid, shape, _float32_resolution(res),
                       "thesis" if compressed else "raw", THESIS_HEADER.size, size)


def _peek_coopd(data) -> MessageInfo:
    _need(data, COOPD_PREFIX.size, "a coopd message prefix")
    _, fmt, header_len = COOPD_PREFIX.unpack_from(data)
    if fmt > COOPD_MAP_VERSION:
        raise MessageVersionError(
            f"coopd map message format version {fmt} is newer than this coopd reads "
            f"(<= {COOPD_MAP_VERSION}); upgrade coopd to read it")
    if fmt < 1:
        raise WireError(f"coopd map message format version {fmt} does not exist")
    if header_len < COOPD_HEADER.size:
        raise WireError(f"header length {header_len} is shorter than the {COOPD_HEADER.size} bytes "
                        f"of format version {fmt}")
    _need(data, header_len, "the coopd map header")
    (_, _, _, vid, map_type, enc, flags, mx, my, mz, ox, oy, oz, res, omx, omy, omz, version, stamp,
     size, crc) = COOPD_HEADER.unpack_from(data)
    shape = _check_shape((mx, my, mz), map_type)
    if flags != 0:
        raise WireError(f"flags 0x{flags:04x} set that format version {fmt} does not define")
    if enc not in ENCODING_NAMES:
        raise WireError(f"unknown encoding id {enc}")
    if not (math.isfinite(res) and res > 0):
        raise WireError(f"resolution {res} is not a positive number")
    for o, om in zip((ox, oy, oz), (omx, omy, omz), strict=True):
        if not (math.isfinite(om) and abs(om - o * res) <= 1e-6 * max(1.0, abs(o * res))):
            raise WireError(f"origin {om} m disagrees with offset {o} cells at {res} m")
    if not math.isfinite(stamp):
        raise WireError(f"timestamp {stamp} is not finite")
    return MessageInfo(MSG_COOPD_MAP, fmt, vid, shape, res, ENCODING_NAMES[enc], header_len, size,
                       (ox, oy, oz), version, stamp, crc)


def decode_payload(payload, encoding: str, n: int) -> np.ndarray:
    """The n flat cells of a payload in a named encoding; WireError if it is malformed."""
    try:
        if encoding == "raw":
            if len(payload) != n:
                raise WireError(f"raw payload holds {len(payload)} bytes for {n} cells")
            cells = np.frombuffer(payload, dtype=np.int8).copy()
            if n and (cells.min() < codec.CELL_MIN or cells.max() > codec.CELL_MAX):
                raise WireError("raw payload holds values outside the cell range -2..100")
            return cells
        if encoding == "thesis":
            return codec.decompress(np.frombuffer(payload, dtype=np.int8), n)
        if encoding == "thesis-zstd":
            return codec.decompress(_unzstd(payload, cap=n), n)
        if encoding == "planes-zstd":
            return planes.decode(payload, n)
    except (CodecError, planes.PlanesError) as e:
        raise WireError(f"{encoding} payload: {e}") from e
    raise WireError(f"unknown encoding {encoding}")


def _unzstd(payload, cap: int) -> np.ndarray:
    """One zstd frame whose declared content size is at most cap bytes, and nothing after it."""
    import zstandard

    try:
        declared = zstandard.frame_content_size(bytes(payload[:18]))
    except zstandard.ZstdError as e:
        raise WireError(f"zstd payload: bad frame header ({e})") from e
    if declared < 0:
        raise WireError("zstd payload does not declare its content size")
    if declared > cap:
        raise WireError(f"zstd payload declares {declared} bytes, more than the {cap} allowed")
    dobj = zstandard.ZstdDecompressor().decompressobj()
    try:
        out = dobj.decompress(bytes(payload))
    except zstandard.ZstdError as e:
        raise WireError(f"zstd payload: {e}") from e
    if len(out) != declared or not dobj.eof or dobj.unused_data:
        raise WireError("zstd payload is truncated, longer than declared, or followed by extra bytes")
    return np.frombuffer(out, dtype=np.int8)


def decode_map(data, limits: DecodeLimits = DEFAULT_LIMITS) -> tuple[OccupancyGrid, MapMeta]:
    """The grid and metadata of a complete map message (type 0 or 1)."""
    if len(data) > limits.max_bytes:
        raise WireError(f"message of {len(data)} bytes exceeds the limit of {limits.max_bytes}")
    info = peek(data)
    info.check(limits)
    if len(data) != info.total_size:
        raise WireError(f"message is {len(data)} bytes but its header announces {info.total_size}")
    payload = memoryview(data)[info.header_size:]
    if info.crc32 is not None and zlib.crc32(payload) != info.crc32:
        raise WireError("payload CRC-32 mismatch: the message is corrupted")
    if not 1e-4 <= info.resolution <= 100.0:
        raise WireError(f"resolution {info.resolution} m is outside 1e-4..100 m")
    cells = decode_payload(payload, info.encoding, info.cells)
    grid = OccupancyGrid(cells.reshape(info.shape), info.resolution, info.offset)
    return grid, MapMeta(info.vehicle_id, info.map_version, info.stamp)


# ---------------------------------------------------------------------------- merge results (type 2)
MERGE_RESULT_VERSION = 1
RESULT_HEADER = struct.Struct("<bBHiQdHHI")
"""type, format version, header length, sender vehicle id, result version, stamp, edge count,
edge size, CRC-32 of the edges (docs/protocol.md §3.3)."""
RESULT_EDGE = struct.Struct("<ii16dffQQB3x")
"""vehicle a, vehicle b, 4x4 transform b -> a (row-major float64), score, overlap, map version of
a, map version of b, flags, 3 bytes padding."""
MAX_EDGES = 64
EDGE_FULL = 1
"""Edge flag: found by a full registration (not by refining a hint)."""
MAX_TRANSLATION_M = 1e6
"""Transforms shifting a map further than this are refused (no swarm flies 1000 km apart)."""


@dataclass(frozen=True)
class MergeEdge:
    """A validated merge of b's map into a's: transform carries b's map frame into a's."""

    a: int
    b: int
    transform: np.ndarray
    score: float
    overlap: float
    version_a: int
    version_b: int
    flags: int = 0


@dataclass(frozen=True)
class MergeResultMessage:
    """The merge results a vehicle publishes: its newest validated edges."""

    vehicle_id: int
    version: int
    """Result version counter: increases whenever the sender publishes new results."""
    stamp: float
    edges: tuple[MergeEdge, ...]

    @property
    def size(self) -> int:
        return RESULT_HEADER.size + len(self.edges) * RESULT_EDGE.size


def _check_edge(e: MergeEdge) -> np.ndarray:
    """The edge's transform as float64 4x4; WireError unless it is a sane rigid transform."""
    from coopd.geometry import check_rigid

    t = np.asarray(e.transform, dtype=np.float64)
    if t.shape == (4, 4) and np.all(np.isfinite(t)) and np.abs(t[:3, :3]).max() > 1.0 + 1e-6:
        raise WireError(f"edge {e.a}->{e.b}: transform is not rigid (rotation entries beyond 1)")
    try:
        t = check_rigid(t, tol=1e-6)
    except ValueError as err:
        raise WireError(f"edge {e.a}->{e.b}: {err}") from None
    if np.abs(t[:3, 3]).max() > MAX_TRANSLATION_M:
        raise WireError(f"edge {e.a}->{e.b}: translation {t[:3, 3]} m is out of range")
    if e.a == e.b:
        raise WireError(f"edge {e.a}->{e.b} joins a map to itself")
    if not (0.0 <= e.score <= 1.0 and 0.0 <= e.overlap <= 1.0):
        raise WireError(f"edge {e.a}->{e.b}: score {e.score} / overlap {e.overlap} outside 0..1")
    return t


def _check_edges(edges: list[MergeEdge]) -> None:
    """_check_edge for every edge, its numeric checks in one numpy pass over all of them (a result of
    29 edges: 1.8 ms edge by edge, 0.4 ms so): the first edge that fails raises its own error."""
    if any(np.shape(e.transform) != (4, 4) for e in edges):
        for e in edges:
            _check_edge(e)
    if not edges:
        return
    t = np.stack([np.asarray(e.transform, dtype=np.float64) for e in edges])
    finite = np.isfinite(t).all(axis=(1, 2))
    t = np.where(np.isfinite(t), t, 0.0)
    r = np.clip(t[:, :3, :3], -2.0, 2.0)  # rotation entries beyond 1 fail below; no overflow on the way
    ok = finite & (np.abs(t[:, :3, :3]).max(axis=(1, 2)) <= 1.0 + 1e-6)
    ok &= np.abs(r @ r.transpose(0, 2, 1) - np.eye(3)).max(axis=(1, 2)) <= 1e-6
    ok &= np.abs(np.linalg.det(r) - 1.0) <= 1e-6
    ok &= np.abs(t[:, 3] - [0.0, 0.0, 0.0, 1.0]).max(axis=1) <= 1e-6
    ok &= np.abs(t[:, :3, 3]).max(axis=1) <= MAX_TRANSLATION_M
    ok &= np.array([e.a != e.b and 0.0 <= e.score <= 1.0 and 0.0 <= e.overlap <= 1.0 for e in edges])
    for i in np.flatnonzero(~ok):
        _check_edge(edges[i])  # the authority, edge by edge: raises with the edge's own reason


def encode_merge_result(msg: MergeResultMessage) -> bytes:
    """A merge-result message (type 2); ValueError (WireError) on edges a decoder would refuse."""
    if len(msg.edges) > MAX_EDGES:
        raise WireError(f"{len(msg.edges)} edges, at most {MAX_EDGES}")
    _check_int32("vehicle id", [msg.vehicle_id, *(v for e in msg.edges for v in (e.a, e.b))])
    if not (0 <= int(msg.version) < 2**64 and math.isfinite(msg.stamp)):
        raise ValueError(f"result version must be 0..2**64-1, stamp finite: {msg.version}, {msg.stamp}")
    body = bytearray()
    _check_edges(list(msg.edges))
    for e in msg.edges:
        t = np.asarray(e.transform, dtype=np.float64)
        if not (0 <= e.version_a < 2**64 and 0 <= e.version_b < 2**64 and 0 <= e.flags < 256):
            raise ValueError(f"edge {e.a}->{e.b}: map versions or flags out of range")
        body += RESULT_EDGE.pack(int(e.a), int(e.b), *t.reshape(-1), float(e.score), float(e.overlap),
                                 int(e.version_a), int(e.version_b), int(e.flags))
    header = RESULT_HEADER.pack(MSG_MERGE_RESULT, MERGE_RESULT_VERSION, RESULT_HEADER.size,
                                int(msg.vehicle_id), int(msg.version), float(msg.stamp), len(msg.edges),
                                RESULT_EDGE.size, zlib.crc32(body))
    return header + bytes(body)


def peek_merge_result(data) -> tuple[int, int, int]:
    """(sender vehicle id, result version, total bytes) from a type-2 header, validated."""
    data = memoryview(data)
    _need(data, RESULT_HEADER.size, "a merge-result header")
    (msg_type, fmt, header_len, vid, version, stamp, count, edge_size,
     _) = RESULT_HEADER.unpack_from(data)
    if msg_type != MSG_MERGE_RESULT:
        raise UnknownMessageType(f"message type {msg_type} is not a merge result")
    if fmt > MERGE_RESULT_VERSION:
        raise MessageVersionError(f"merge-result format version {fmt} is newer than this coopd reads "
                                  f"(<= {MERGE_RESULT_VERSION})")
    if fmt < 1:
        raise WireError(f"merge-result format version {fmt} does not exist")
    if header_len != RESULT_HEADER.size or edge_size != RESULT_EDGE.size:
        raise WireError(f"header length {header_len} / edge size {edge_size} differ from format "
                        f"{fmt}'s {RESULT_HEADER.size} / {RESULT_EDGE.size}")
    if count > MAX_EDGES:
        raise WireError(f"{count} edges, at most {MAX_EDGES}")
    if not math.isfinite(stamp):
        raise WireError(f"timestamp {stamp} is not finite")
    return vid, version, header_len + count * edge_size


def decode_merge_result(data) -> MergeResultMessage:
    """A complete merge-result message, every field checked (sizes before anything is allocated)."""
    vid, version, total = peek_merge_result(data)
    if len(data) != total:
        raise WireError(f"message is {len(data)} bytes but its header announces {total}")
    _, _, _, _, _, stamp, count, _, crc = RESULT_HEADER.unpack_from(data)
    body = memoryview(data)[RESULT_HEADER.size:]
    if zlib.crc32(body) != crc:
        raise WireError("merge-result CRC-32 mismatch: the message is corrupted")
    edges = []
    for i in range(count):
        f = RESULT_EDGE.unpack_from(body, i * RESULT_EDGE.size)
        e = MergeEdge(f[0], f[1], np.array(f[2:18], dtype=np.float64).reshape(4, 4), f[18], f[19],
                      f[20], f[21], f[22])
        if e.flags & ~EDGE_FULL:
            raise WireError(f"edge {e.a}->{e.b}: flags 0x{e.flags:02x} not defined")
        edges.append(e)
    _check_edges(edges)
    return MergeResultMessage(vid, version, stamp, tuple(edges))

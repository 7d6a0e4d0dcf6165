"""The `planes-zstd` payload encoding: a lossless cell-aware transform followed by zstd.

Cells are split into a 2-bit class plane (unknown / 0 / 100 / escape), a nibble stream for
the escaped cells (the other HIMM values 10..90 and -2) and a raw byte stream for anything
else; each stream is one zstd frame. Four cells per plane byte let zstd's byte-wise entropy
coder spend well under one bit on a free cell, which is where plain zstd loses (the goal:
smaller than zstd -19 at the speed of zstd -3). Layout in docs/protocol.md §4.
"""

import struct

import numpy as np

from . import planes_kernels as k

LEVEL = 1
"""zstd level of the three frames: measured best ratio and speed on planes (scripts/bench codec)."""
PREFIX = struct.Struct("<III")


class PlanesError(ValueError):
    """A malformed planes payload."""


def encode(cells: np.ndarray) -> bytes:
    """The planes-zstd payload of flat int8 cells (values -2..100)."""
    import zstandard

    cells = np.asarray(cells)
    if cells.dtype != np.int8:
        raise ValueError(f"cells must be int8, got {cells.dtype}")
    cells = np.ascontiguousarray(cells).reshape(-1)
    n = cells.size
    plane = np.zeros((n + 3) // 4, dtype=np.uint8)
    nibbles = np.zeros((n + 1) // 2 + 1, dtype=np.uint8)  # +1: the kernel writes one ahead
    raw = np.empty(n + 1, dtype=np.int8)
    words = cells[: n // 8 * 8].view(np.uint64)
    nn, nr, bad = k.encode(cells, words, plane, nibbles, raw)
    if bad >= 0:
        raise ValueError(f"cell {bad} holds {int(cells[bad])}, outside the cell range -2..100")
    zc = zstandard.ZstdCompressor(level=LEVEL, write_content_size=True)
    frames = [zc.compress(plane.tobytes()), zc.compress(nibbles[: (nn + 1) // 2].tobytes()),
              zc.compress(raw[:nr].tobytes())]
    return PREFIX.pack(*(len(f) for f in frames)) + b"".join(frames)


def _frame(data: bytes, exact: int | None, cap: int, what: str) -> np.ndarray:
    import zstandard

    try:
        declared = zstandard.frame_content_size(data[:18])
    except zstandard.ZstdError as e:
        raise PlanesError(f"{what}: bad zstd frame header ({e})") from e
    if declared < 0:
        raise PlanesError(f"{what}: zstd frame does not declare its content size")
    if (exact is not None and declared != exact) or declared > cap:
        raise PlanesError(f"{what}: zstd frame declares {declared} bytes, expected "
                          f"{exact if exact is not None else f'at most {cap}'}")
    dobj = zstandard.ZstdDecompressor().decompressobj()
    try:
        out = dobj.decompress(data)
    except zstandard.ZstdError as e:
        raise PlanesError(f"{what}: {e}") from e
    if len(out) != declared or not dobj.eof or dobj.unused_data:
        raise PlanesError(f"{what}: zstd frame truncated, longer than declared, or followed by extra bytes")
    return np.frombuffer(out, dtype=np.uint8)


_ERRORS = {
    k.ERR_NIBBLES: "escape nibbles do not match the escapes of the class plane",
    k.ERR_RAW: "raw bytes do not match the raw escapes of the nibble stream",
    k.ERR_BAD_NIBBLE: "undefined escape nibble",
    k.ERR_BAD_RAW_VALUE: "raw escape byte outside the cell range -2..100",
    k.ERR_PADDING: "class plane has bits set beyond the last cell",
}


def decode(payload, n: int) -> np.ndarray:
    """The n cells of a planes-zstd payload; PlanesError when it is malformed in any way."""
    payload = bytes(payload)
    if len(payload) < PREFIX.size:
        raise PlanesError(f"payload of {len(payload)} bytes is shorter than its {PREFIX.size}-byte prefix")
    sizes = PREFIX.unpack_from(payload)
    if PREFIX.size + sum(sizes) != len(payload):
        raise PlanesError(f"frame sizes {sizes} do not add up to the payload of {len(payload)} bytes")
    a = PREFIX.size
    b = a + sizes[0]
    c = b + sizes[1]
    plane = _frame(payload[a:b], (n + 3) // 4, (n + 3) // 4, "class plane")
    nibbles = _frame(payload[b:c], None, (n + 1) // 2, "escape nibbles")
    raw = _frame(payload[c:], None, n, "raw escapes").view(np.int8)
    out = np.full(n, -1, dtype=np.int8)
    status, where = k.decode(plane, plane[: plane.size // 8 * 8].view(np.uint64), nibbles, raw, out)
    if status != k.OK:
        raise PlanesError(f"{_ERRORS[status]} (at cell {where})")
    return out

"""The thesis two-level map codec (thesis §7.1, notes §4): occurrence runs and sequence runs.

compress() turns the row-major int8 cell stream into the canonical compressed stream;
decompress() is its exact inverse and treats every stream as hostile: it validates the whole
stream against the announced cell count before allocating the output.
"""

import numpy as np

from . import codec_kernels as k

CELL_MIN = k.CELL_MIN
CELL_MAX = k.CELL_MAX
BASE_MARKER = k.BASE_MARKER
LOWEST_MARKER = k.LOWEST_MARKER
MAX_COUNT = k.MAX_COUNT
MAX_EXPANDED = 1 << 40
"""No stream may announce more cells than this (keeps run arithmetic far from int64 overflow)."""


class CodecError(ValueError):
    """A cell stream that cannot be compressed, or a compressed stream that is malformed."""


_MESSAGES = {
    k.ERR_TRUNCATED: "stream ends inside a run triple at byte {pos}",
    k.ERR_BAD_MARKER: "byte {pos} holds {byte}, which is neither a cell value (-2..100) nor a run "
                      "marker (-127..-10)",
    k.ERR_BAD_VALUE: "run value {byte} at byte {pos} is not a cell value (-2..100)",
    k.ERR_BAD_COUNT: "run count {byte} at byte {pos} is not in 1..127",
    k.ERR_TOO_LONG: "stream expands beyond the announced {expected} cells (at byte {pos})",
    k.ERR_TOO_SHORT: "stream expands to fewer than the announced {expected} cells",
}


def _as_int8(data, what: str) -> np.ndarray:
    if isinstance(data, (bytes, bytearray, memoryview)):
        return np.frombuffer(data, dtype=np.int8)
    arr = np.asarray(data)
    if arr.dtype != np.int8:
        raise CodecError(f"{what} must be int8, got {arr.dtype}")
    return np.ascontiguousarray(arr.reshape(-1))


def _check_cells(bad_index: int, cells: np.ndarray, base: int = 0) -> None:
    if bad_index >= 0:
        raise CodecError(f"cell {base + bad_index} holds {int(cells[bad_index])}, outside the cell "
                         f"range {CELL_MIN}..{CELL_MAX}")


def _words(cells: np.ndarray) -> np.ndarray:
    return cells[: cells.size // 8 * 8].view(np.uint64)


def compress(cells_flat_int8: np.ndarray) -> np.ndarray:
    """The canonical thesis stream (int8, never -128) of a flat int8 cell array."""
    cells = _as_int8(cells_flat_int8, "cells")
    out = np.empty(cells.size + k.EMIT_SLACK, dtype=np.int8)
    o, v, n, bad = k.compress_chunk(cells, _words(cells), out, np.int8(0), np.int64(0))
    _check_cells(bad, cells)
    o = k.emit_run(out, o, np.int8(v), np.int64(n))
    return out[:o].copy()


def decompress(stream, expected_size: int) -> np.ndarray:
    """The expected_size cells a stream encodes; CodecError unless it encodes exactly that many."""
    data = _as_int8(stream, "stream")
    expected = int(expected_size)
    if not 0 <= expected <= MAX_EXPANDED:
        raise CodecError(f"announced size {expected} is outside 0..{MAX_EXPANDED} cells")
    status, pos = k.measure(data, np.int64(expected))
    if status != k.OK:
        byte = int(data[pos]) if pos < data.size else None
        raise CodecError(_MESSAGES[status].format(pos=int(pos), byte=byte, expected=expected))
    out = np.empty(expected, dtype=np.int8)
    k.expand(data, out)
    return out


class StreamCompressor:
    """Compress a cell stream fed in chunks; the result equals compress() of the concatenation."""

    def __init__(self):
        self._pend_v = np.int8(0)
        self._pend_n = np.int64(0)
        self._seen = 0

    def feed(self, chunk: np.ndarray) -> np.ndarray:
        """Compressed bytes that are final after this chunk (possibly empty)."""
        cells = _as_int8(chunk, "cells")
        out = np.empty(cells.size + k.EMIT_SLACK, dtype=np.int8)
        o, v, n, bad = k.compress_chunk(cells, _words(cells), out, self._pend_v, self._pend_n)
        _check_cells(bad, cells, self._seen)
        self._seen += cells.size
        self._pend_v, self._pend_n = np.int8(v), np.int64(n)
        return out[:o].copy()

    def finish(self) -> np.ndarray:
        """The bytes of the last pending run."""
        out = np.empty(k.EMIT_SLACK, dtype=np.int8)
        o = k.emit_run(out, 0, self._pend_v, self._pend_n)
        self._pend_n = np.int64(0)
        return out[:o].copy()

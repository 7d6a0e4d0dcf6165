"""numba kernels of the thesis two-level map codec (thesis §7.1, notes §4).

Stream grammar: a literal is a cell value (-2..100); a triple (M, v, c) with -127 <= M <= -10,
v a cell value and 1 <= c <= 127 expands to c * 127**L copies of v, L = -10 - M.
"""

import numba as nb
import numpy as np

from coopd.kernel_cache import CACHE as KERNEL_CACHE

_JIT = {"nogil": True, "cache": KERNEL_CACHE, "boundscheck": False}

CELL_MIN = -2
CELL_MAX = 100
BASE_MARKER = -10
LOWEST_MARKER = -127
MAX_COUNT = 127
SHORT_RUN = 16
"""Run length after which the scan switches from bytes to uint64 words."""
EMIT_SLACK = 64
"""Extra output bytes a chunk may need beyond its own length (the pending run's triples)."""

# status codes shared with codec.py (negative = error)
OK = 0
ERR_BAD_CELL = -1
ERR_TRUNCATED = -2
ERR_BAD_MARKER = -3
ERR_BAD_VALUE = -4
ERR_BAD_COUNT = -5
ERR_TOO_LONG = -6
ERR_TOO_SHORT = -7


@nb.njit(**_JIT)
def _put_triple(out, o, marker, v, c):
    out[o] = marker
    out[o + 1] = v
    out[o + 2] = c
    return o + 3


@nb.njit(**_JIT)
def emit_run(out, o, v, n):
    """Write the canonical encoding of n copies of v at out[o:]; return the new end.

    This is the fixed point of the thesis passes, computed directly from n's base-127 digits:
    level L's digit d becomes (-10-L, v, d) when d >= 2, a lone level-(L-1) full triple
    (-10-(L-1), v, 127) when d == 1 (one triple cannot form a sequence); the level-0 digit
    becomes a triple whenever the run has >= 3 cells, and literals when it has 1 or 2.
    Higher levels come first, as the left-to-right passes leave them.
    """
    if n < 3:
        for _ in range(n):
            out[o] = v
            o += 1
        return o
    p = np.int64(1)
    level = 0
    while p <= n // MAX_COUNT:
        p *= MAX_COUNT
        level += 1
    rest = n
    while level >= 0:
        d = rest // p
        rest -= d * p
        if d > 0:
            if level == 0:
                o = _put_triple(out, o, BASE_MARKER, v, d)
            elif d >= 2:
                o = _put_triple(out, o, BASE_MARKER - level, v, d)
            else:
                o = _put_triple(out, o, BASE_MARKER - level + 1, v, MAX_COUNT)
        p //= MAX_COUNT
        level -= 1
    return o


@nb.njit(**_JIT)
def compress_chunk(cells, words, out, pend_v, pend_n):
    """Encode cells after a pending run (pend_v repeated pend_n times) into out.

    Every run that ends inside the chunk is emitted; the last one stays pending so that a
    stream fed in chunks encodes exactly like the whole array. out needs len(cells) +
    EMIT_SLACK bytes; words is cells[:len // 8 * 8] viewed as uint64. Returns (bytes
    written, pending value, pending count, bad index), bad index >= 0 naming the first cell
    outside -2..100.

    Runs are scanned byte by byte up to SHORT_RUN cells, then by whole words (long unknown
    runs go at memory speed). One flat loop on purpose: calling a helper with array
    arguments per run costs numba reference counting that dominates on noisy maps.
    """
    n = cells.size
    nw = words.size
    o = 0
    i = 0
    v = pend_v
    run = pend_n
    continuing = run > 0
    while i < n:
        if not continuing:
            if run > 0:
                o = emit_run(out, o, v, run)
            v = cells[i]
            if v < CELL_MIN or v > CELL_MAX:
                return o, v, 0, i
            run = 0
        continuing = False
        # extend the run of v that starts at i
        j = i
        short = min(n, i + SHORT_RUN)
        while j < short and cells[j] == v:
            j += 1
        if j == short and j < n:
            while j < n and (j & 7) != 0 and cells[j] == v:
                j += 1
            if j < n and (j & 7) == 0:
                pattern = np.uint64(np.uint8(v)) * np.uint64(0x0101010101010101)
                w = j >> 3
                while w + 4 <= nw:
                    if ((words[w] ^ pattern) | (words[w + 1] ^ pattern) | (words[w + 2] ^ pattern)
                            | (words[w + 3] ^ pattern)) != 0:
                        break
                    w += 4
                j = w << 3
                while j < n and cells[j] == v:
                    j += 1
        run += j - i
        i = j
    return o, v, run, -1


@nb.njit(**_JIT)
def measure(stream, expected):
    """Validate a stream and check it expands to exactly `expected` cells, allocating nothing.

    Returns (status, stream position of the problem).
    """
    s = stream.size
    total = np.int64(0)
    i = 0
    while i < s:
        b = stream[i]
        if b >= CELL_MIN and b <= CELL_MAX:
            if total >= expected:
                return ERR_TOO_LONG, i
            total += 1
            i += 1
            continue
        if b > BASE_MARKER or b < LOWEST_MARKER:
            return ERR_BAD_MARKER, i
        if i + 2 >= s:
            return ERR_TRUNCATED, i
        v = stream[i + 1]
        if v < CELL_MIN or v > CELL_MAX:
            return ERR_BAD_VALUE, i + 1
        c = np.int64(stream[i + 2])
        if c < 1:
            return ERR_BAD_COUNT, i + 2
        room = expected - total
        level = BASE_MARKER - b
        count = c
        while level > 0:
            if count > room:
                return ERR_TOO_LONG, i
            count *= MAX_COUNT
            level -= 1
        if count > room:
            return ERR_TOO_LONG, i
        total += count
        i += 3
    if total != expected:
        return ERR_TOO_SHORT, s
    return OK, s


@nb.njit(**_JIT)
def expand(stream, out):
    """Expand a stream that measure() accepted for out.size cells into out."""
    s = stream.size
    i = 0
    o = 0
    while i < s:
        b = stream[i]
        if b >= CELL_MIN:
            out[o] = b
            o += 1
            i += 1
            continue
        v = stream[i + 1]
        count = np.int64(stream[i + 2])
        for _ in range(BASE_MARKER - b):
            count *= MAX_COUNT
        out[o:o + count] = v
        o += count
        i += 3
    return o

"""numba kernels of the `planes` transform: cells -> 2-bit class plane + escape nibbles + bytes.

Class codes (2 bits, cell i at bits 2*(i%4) of plane byte i//4): 0 unknown (-1), 1 free 0,
2 occupied 100, 3 escape -> the next nibble (cell order, low nibble first): 0..9 index
NIBBLE_VALUES, 15 -> the next raw byte (any cell value); nibbles 10..14 are invalid.
"""

import numba as nb
import numpy as np

_JIT = {"nogil": True, "cache": True, "boundscheck": False}

NIBBLE_VALUES = np.array([10, 20, 30, 40, 50, 60, 70, 80, 90, -2], dtype=np.int8)
"""The values HIMM updates (±10, -30 from 50) reach, and inaccessible: one nibble each."""
RAW_NIBBLE = 15
ALL_UNKNOWN = np.uint64(0xFFFFFFFFFFFFFFFF)

OK = 0
ERR_BAD_CELL = -1
ERR_NIBBLES = -2
ERR_RAW = -3
ERR_BAD_NIBBLE = -4
ERR_BAD_RAW_VALUE = -5
ERR_PADDING = -6


@nb.njit(**_JIT)
def _nibble_code(c):
    for k in range(NIBBLE_VALUES.size):
        if NIBBLE_VALUES[k] == c:
            return k
    return RAW_NIBBLE


@nb.njit(**_JIT)
def encode(cells, words, plane, nibbles, raw):
    """Fill zeroed plane (ceil(n/4)), zeroed nibbles (ceil(n/2)) and raw (n) from the cells.

    words is cells[:n // 8 * 8] viewed as uint64: blocks of 32 unknown cells are skipped
    whole, so the cost follows the known cells. Returns (nibbles used, raw bytes used, bad
    cell index or -1).
    """
    n = cells.size
    nn = 0
    nr = 0
    nw = words.size
    w = 0
    while w < nw:
        if w + 4 <= nw and (words[w] & words[w + 1] & words[w + 2] & words[w + 3]) == ALL_UNKNOWN:
            w += 4
            continue
        if words[w] == ALL_UNKNOWN:
            w += 1
            continue
        for i in range(8 * w, 8 * w + 8):
            c = cells[i]
            if c == -1:
                continue
            if c < -2 or c > 100:
                return nn, nr, i
            if c == 0:
                code = 1
            elif c == 100:
                code = 2
            else:
                code = 3
                k = _nibble_code(c)
                nibbles[nn >> 1] |= np.uint8(k << (4 * (nn & 1)))
                nn += 1
                if k == RAW_NIBBLE:
                    raw[nr] = c
                    nr += 1
            plane[i >> 2] |= np.uint8(code << (2 * (i & 3)))
        w += 1
    for i in range(8 * nw, n):
        c = cells[i]
        if c == -1:
            continue
        if c < -2 or c > 100:
            return nn, nr, i
        if c == 0:
            code = 1
        elif c == 100:
            code = 2
        else:
            code = 3
            k = _nibble_code(c)
            nibbles[nn >> 1] |= np.uint8(k << (4 * (nn & 1)))
            nn += 1
            if k == RAW_NIBBLE:
                raw[nr] = c
                nr += 1
        plane[i >> 2] |= np.uint8(code << (2 * (i & 3)))
    return nn, nr, -1


@nb.njit(**_JIT)
def decode(plane, plane_words, nibbles, raw, out):
    """Fill out (pre-set to -1) from the three streams; plane_words views plane as uint64.

    Every stream must be consumed exactly and unused bits must be zero. Returns (status,
    cell index where it failed).
    """
    n = out.size
    nn_cap = nibbles.size * 2
    nr_cap = raw.size
    nn = 0
    nr = 0
    nbytes = plane.size
    nw = plane_words.size
    b = 0
    while b < nbytes:
        if (b & 7) == 0 and (b >> 3) < nw and plane_words[b >> 3] == 0:
            b += 8
            continue
        byte = plane[b]
        if byte != 0:
            for j in range(4):
                code = (byte >> (2 * j)) & 3
                if code == 0:
                    continue
                i = 4 * b + j
                if i >= n:
                    return ERR_PADDING, i
                if code == 1:
                    out[i] = 0
                elif code == 2:
                    out[i] = 100
                else:
                    if nn >= nn_cap:
                        return ERR_NIBBLES, i
                    k = (nibbles[nn >> 1] >> (4 * (nn & 1))) & 15
                    nn += 1
                    if k < NIBBLE_VALUES.size:
                        out[i] = NIBBLE_VALUES[k]
                    elif k == RAW_NIBBLE:
                        if nr >= nr_cap:
                            return ERR_RAW, i
                        v = raw[nr]
                        nr += 1
                        if v < -2 or v > 100:
                            return ERR_BAD_RAW_VALUE, i
                        out[i] = v
                    else:
                        return ERR_BAD_NIBBLE, i
        b += 1
    if (nn + 1) >> 1 != nibbles.size or (nn & 1 and (nibbles[nn >> 1] >> 4) != 0):
        return ERR_NIBBLES, n
    if nr != nr_cap:
        return ERR_RAW, n
    return OK, n

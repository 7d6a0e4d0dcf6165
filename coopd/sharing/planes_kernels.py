"""numba kernels of the `planes` transform: cells -> 2-bit class plane + escape nibbles + bytes.

Class codes (2 bits, cell i at bits 2*(i%4) of plane byte i//4): 0 unknown (-1), 1 free 0,
2 occupied 100, 3 escape -> the next nibble (cell order, low nibble first): 0..9 index
NIBBLE_VALUES, 15 -> the next raw byte (any cell value); nibbles 10..14 are invalid.
"""

import numba as nb
import numpy as np

from coopd.kernel_cache import CACHE as KERNEL_CACHE

_JIT = {"nogil": True, "cache": KERNEL_CACHE, "boundscheck": False}

NIBBLE_VALUES = np.array([10, 20, 30, 40, 50, 60, 70, 80, 90, -2], dtype=np.int8)
"""The values HIMM updates (±10, -30 from 50) reach, and inaccessible: one nibble each."""
RAW_NIBBLE = 15
ALL_UNKNOWN = np.uint64(0xFFFFFFFFFFFFFFFF)
ALL_OCCUPIED = np.uint64(0x6464646464646464)
FREE_BYTE = np.uint8(0x55)
"""Plane byte of four free (0) cells."""
OCCUPIED_BYTE = np.uint8(0xAA)
"""Plane byte of four occupied (100) cells."""

OK = 0
ERR_BAD_CELL = -1
ERR_NIBBLES = -2
ERR_RAW = -3
ERR_BAD_NIBBLE = -4
ERR_BAD_RAW_VALUE = -5
ERR_PADDING = -6


def _lookup_tables():
    """By cell byte: its 2-bit class (4 = not a cell value) and its escape nibble."""
    cls = np.full(256, 4, dtype=np.uint8)
    nib = np.full(256, RAW_NIBBLE, dtype=np.uint8)
    for v in range(-2, 101):
        cls[v & 0xFF] = 3
    cls[0xFF], cls[0], cls[100] = 0, 1, 2
    for k, v in enumerate(NIBBLE_VALUES):
        nib[int(v) & 0xFF] = k
    return cls, nib


CLASS_OF, NIBBLE_OF = _lookup_tables()


@nb.njit(**_JIT)
def _encode_cells(cells, lo, hi, plane, nibbles, raw, nn, nr):
    """Encode cells[lo:hi] (lo a multiple of 4) into zeroed streams; (nn, nr, bad index)."""
    for i in range(lo, hi):
        c = cells[i]
        code = CLASS_OF[np.uint8(c)]
        if code >= 3:
            if code == 4:
                return nn, nr, i
            k = NIBBLE_OF[np.uint8(c)]
            nibbles[nn >> 1] |= np.uint8(k << (4 * (nn & 1)))
            nn += 1
            if k == RAW_NIBBLE:
                raw[nr] = c
                nr += 1
        plane[i >> 2] |= np.uint8(code << (2 * (i & 3)))
    return nn, nr, -1


@nb.njit(**_JIT)
def encode(cells, words, plane, nibbles, raw):
    """Fill zeroed plane (ceil(n/4)), zeroed nibbles (ceil(n/2) + 1) and raw (n + 1) from the cells.

    words is cells[:n // 8 * 8] viewed as uint64: blocks of 32 unknown cells are skipped
    whole, so the cost follows the known cells; a plane byte is built in a register from
    table look-ups. Returns (nibbles used, raw bytes used, bad cell index or -1).
    """
    nn = 0
    nr = 0
    nw = words.size
    w = 0
    while w < nw:
        if w + 4 <= nw and (words[w] & words[w + 1] & words[w + 2] & words[w + 3]) == ALL_UNKNOWN:
            w += 4
            continue
        word = words[w]
        if word == ALL_UNKNOWN:
            w += 1
            continue
        base = 8 * w
        if word == 0 or word == ALL_OCCUPIED:  # 8 certain cells: common inside rooms and walls
            plane[base >> 2] = plane[(base >> 2) + 1] = FREE_BYTE if word == 0 else OCCUPIED_BYTE
            w += 1
            continue
        invalid = False
        for half in range(2):
            byte = np.uint8(0)
            for j in range(4):
                i = base + 4 * half + j
                c = cells[i]
                code = CLASS_OF[np.uint8(c)]
                invalid |= code == 4
                # branch-free escape bookkeeping: noisy free space makes escapes unpredictable
                esc = np.int64(code == 3)
                k = NIBBLE_OF[np.uint8(c)]
                nibbles[nn >> 1] |= np.uint8((k * esc) << (4 * (nn & 1)))
                nn += esc
                raw[nr] = c
                nr += esc & np.int64(k == RAW_NIBBLE)
                byte |= np.uint8((code & 3) << (2 * j))
            plane[(base >> 2) + half] = byte
        if invalid:
            for i in range(base, base + 8):
                if CLASS_OF[np.uint8(cells[i])] == 4:
                    return nn, nr, i
        w += 1
    return _encode_cells(cells, 8 * nw, cells.size, plane, nibbles, raw, nn, nr)


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

"""numba kernels of map deltas: brick hashes, and moving brick cells between a grid and a flat stream."""

import numba as nb
import numpy as np

from coopd.grid.cells import UNKNOWN
from coopd.kernel_cache import CACHE as KERNEL_CACHE

_JIT = {"nogil": True, "cache": KERNEL_CACHE, "boundscheck": False}

EMPTY_HASH = np.uint64(0x9E3779B97F4A7C15)
"""The hash of a brick without a known cell (its value wherever the brick lies)."""
_MUL = np.uint64(0xFF51AFD7ED558CCD)


@nb.njit(**_JIT)
def brick_hashes(cells, grid_lo, lattice_lo, edge, out):
    """out[bx, by, bz] = a 64-bit hash of the known cells of brick lattice_lo + (bx, by, bz): each known
    cell's position inside its brick and its value, so it does not depend on where the grid's box cuts
    the brick (cells outside the grid are unknown). Bricks without known cells hash to EMPTY_HASH."""
    mx, my, mz = cells.shape
    out[:] = EMPTY_HASH
    for x in range(mx):
        kx = x + grid_lo[0]
        bx = kx // edge
        px = kx - bx * edge
        for y in range(my):
            ky = y + grid_lo[1]
            by = ky // edge
            py = ky - by * edge
            row = cells[x, y]
            for z in range(mz):
                v = row[z]
                if v == UNKNOWN:
                    continue
                kz = z + grid_lo[2]
                bz = kz // edge
                pz = kz - bz * edge
                i, j, k = bx - lattice_lo[0], by - lattice_lo[1], bz - lattice_lo[2]
                h = out[i, j, k]
                word = np.uint64(((px * edge + py) * edge + pz) * 256 + (v & 0xFF))
                h = (h ^ word) * _MUL
                h ^= h >> np.uint64(29)
                out[i, j, k] = h
    return out


@nb.njit(**_JIT)
def brick_boxes(bricks, edge, grid_lo, shape):
    """(K, 6) array coordinates [x0, y0, z0, x1, y1, z1) of each brick (brick coordinates, (K, 3)) cut
    to the grid box (grid_lo, shape); a brick outside the box gets an empty box."""
    out = np.zeros((bricks.shape[0], 6), dtype=np.int64)
    for n in range(bricks.shape[0]):
        for a in range(3):
            lo = bricks[n, a] * edge - grid_lo[a]
            hi = lo + edge
            lo = min(max(lo, 0), shape[a])
            hi = min(max(hi, 0), shape[a])
            out[n, a] = lo
            out[n, a + 3] = max(hi, lo)
    return out


@nb.njit(**_JIT)
def copy_boxes(cells, boxes, stream, to_stream):
    """Move the cells of every box to the flat stream (to_stream) or back: box after box, each
    row-major (x, y, z). Returns the number of stream cells used."""
    o = 0
    for n in range(boxes.shape[0]):
        for x in range(boxes[n, 0], boxes[n, 3]):
            for y in range(boxes[n, 1], boxes[n, 4]):
                for z in range(boxes[n, 2], boxes[n, 5]):
                    if to_stream:
                        stream[o] = cells[x, y, z]
                    else:
                        cells[x, y, z] = stream[o]
                    o += 1
    return o

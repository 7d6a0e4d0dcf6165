"""Combining grids of one frame by the thesis' Table 3 (§8.9).

Rule, cell by cell (a = the reference map W, b = the other map):
- unknown + x = x; inaccessible + known = the known value (inaccessible only where no map knows more);
- free + free = free, keeping the lower probability (the more certain);
- occupied + anything known = occupied, keeping the higher probability.
The rule is symmetric, so fusion order only matters through growth, never through values.
"""

import numpy as np

from . import kernels
from .cells import CELL_DTYPE, OCCUPIED_THRESHOLD, UNKNOWN
from .grid import OccupancyGrid


def fuse_values(a: np.ndarray, b: np.ndarray, threshold: int = OCCUPIED_THRESHOLD) -> np.ndarray:
    """Table 3 on two same-shaped int8 arrays, returning a new array."""
    a = np.asarray(a, dtype=CELL_DTYPE)
    b = np.asarray(b, dtype=CELL_DTYPE)
    if a.shape != b.shape:
        raise ValueError(f"shapes differ: {a.shape} vs {b.shape}")
    out = np.ascontiguousarray(a).copy()
    kernels.fuse_flat(out.reshape(-1), np.ascontiguousarray(b).reshape(-1), threshold)
    return out


def fuse_into(dst: OccupancyGrid, src: OccupancyGrid, threshold: int = OCCUPIED_THRESHOLD) -> None:
    """Fuse src's known cells into dst (same frame and resolution), growing dst to hold them."""
    dst._check_same_resolution(src)
    bounds = src.known_key_bounds()
    if bounds is None:
        return
    lo, hi = bounds
    dst.ensure(lo, hi)
    kernels.fuse_block(dst.block(lo, hi), src.block(lo, hi), threshold)


def fuse(a: OccupancyGrid, b: OccupancyGrid, threshold: int = OCCUPIED_THRESHOLD) -> OccupancyGrid:
    """A new grid covering both inputs' known cells, fused by Table 3."""
    out = a.copy()
    fuse_into(out, b, threshold)
    return out


def empty_like_box(lo_key, hi_key, resolution: float, growth) -> OccupancyGrid:
    """An all-unknown grid covering the inclusive key box lo..hi."""
    lo = np.asarray(lo_key, dtype=np.int64)
    shape = tuple(int(v) for v in np.asarray(hi_key, dtype=np.int64) - lo + 1)
    return OccupancyGrid(np.full(shape, UNKNOWN, dtype=CELL_DTYPE), resolution, lo, growth)

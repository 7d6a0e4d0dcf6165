"""A grid at another resolution in the same frame, so that maps of different resolutions can merge.

Cell key k covers [(k - 0.5) r, (k + 0.5) r) on each axis. Coarsening, a new cell takes the most
telling value of the old cells whose centres it holds (occupied over free over inaccessible over
unknown, the highest occupancy among them): every old cell counts in exactly one new cell, so a
surface one old cell thick survives and does not thicken. Refining, a new cell takes the old cell
under its centre (refining, then coarsening back, gives the grid back). Pooling is separable per
axis (a max over a box is a max over its rows), so the work is a few whole-array passes.
"""

import numpy as np

from .cells import INACCESSIBLE, UNKNOWN
from .grid import GridTooLarge, OccupancyGrid

_EPS = 1e-9


def _source_ranges(lo_key: int, count: int, ratio: float, src_lo: int, src_count: int):
    """For new keys lo_key..lo_key+count-1: first and last old array index each reads, and whether
    any old cell lies under it. ratio = new resolution / old resolution."""
    t = np.arange(lo_key, lo_key + count, dtype=np.float64)
    if ratio >= 1.0:
        first = np.ceil((t - 0.5) * ratio - _EPS).astype(np.int64)
        last = np.ceil((t + 0.5) * ratio - _EPS).astype(np.int64) - 1
    else:
        first = last = np.floor(t * ratio + 0.5).astype(np.int64)
    first, last = first - src_lo, last - src_lo
    inside = (last >= 0) & (first <= src_count - 1)
    return np.clip(first, 0, src_count - 1), np.clip(last, 0, src_count - 1), inside


def _pool(values: np.ndarray, axis: int, first: np.ndarray, last: np.ndarray) -> np.ndarray:
    """Max of values[first..last] along axis, for every new index."""
    out = np.take(values, first, axis=axis)
    for step in range(1, int((last - first).max(initial=0)) + 1):
        np.maximum(out, np.take(values, np.minimum(first + step, last), axis=axis), out=out)
    return out


def resample(grid: OccupancyGrid, resolution: float) -> OccupancyGrid:
    """`grid` at `resolution` (metres), same frame; the grid itself when the resolution is the same.
    Raises GridTooLarge when the result would exceed the grid's growth budget."""
    if abs(resolution - grid.resolution) <= 1e-9 * grid.resolution:
        return grid
    ratio = resolution / grid.resolution
    if ratio >= 1.0:  # the new cells holding the old centres
        lo_key = np.floor(grid.offset / ratio + 0.5 + _EPS).astype(np.int64)
        hi_key = np.floor((grid.offset + np.array(grid.shape) - 1) / ratio + 0.5 + _EPS).astype(np.int64)
    else:  # the new cells whose centres the old cells hold
        lo_key = np.ceil((grid.offset - 0.5) / ratio - _EPS).astype(np.int64)
        hi_key = np.ceil((grid.offset + np.array(grid.shape) - 0.5) / ratio - _EPS).astype(np.int64) - 1
    shape = tuple(int(v) for v in np.maximum(hi_key - lo_key + 1, 1))
    if int(np.prod(shape, dtype=np.int64)) > grid.growth.max_cells:
        raise GridTooLarge(f"{grid.shape} cells at {grid.resolution} m become {shape} at {resolution} m, "
                           f"over {grid.growth.max_cells} cells")
    # rank unknown below inaccessible so that the max keeps any knowledge: swap -1 and -2
    values = grid.cells.copy()
    unknown, inaccessible = values == UNKNOWN, values == INACCESSIBLE
    values[unknown], values[inaccessible] = INACCESSIBLE, UNKNOWN
    outside = np.zeros(shape, dtype=bool)
    for axis in range(3):
        first, last, inside = _source_ranges(int(lo_key[axis]), shape[axis], ratio, int(grid.offset[axis]),
                                             grid.shape[axis])
        values = _pool(values, axis, first, last)
        view = [np.newaxis] * 3
        view[axis] = slice(None)
        outside |= ~inside[tuple(view)]
    values[outside] = INACCESSIBLE  # still swapped: this is unknown
    unknown, inaccessible = values == INACCESSIBLE, values == UNKNOWN
    values[unknown], values[inaccessible] = UNKNOWN, INACCESSIBLE
    return OccupancyGrid(values, resolution, lo_key, grid.growth)

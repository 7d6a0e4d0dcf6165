"""Cell selections shared by the exports: keys and values of the cells of one class."""

import numpy as np

from coopd.grid import OccupancyGrid
from coopd.grid.cells import OCCUPIED_THRESHOLD


def occupied_cells(grid: OccupancyGrid, threshold: int = OCCUPIED_THRESHOLD):
    """(keys (n, 3) int64, values (n,) int8) of the occupied cells, in storage order."""
    idx = np.flatnonzero(grid.flat >= threshold)
    return _keys(grid, idx), grid.flat[idx]


def known_cells(grid: OccupancyGrid):
    """(keys (n, 3) int64, values (n,) int8) of the free and occupied cells (p in 0..100)."""
    idx = np.flatnonzero(grid.flat >= 0)
    return _keys(grid, idx), grid.flat[idx]


def _keys(grid: OccupancyGrid, idx: np.ndarray) -> np.ndarray:
    return np.stack(np.unravel_index(idx, grid.shape), axis=1).astype(np.int64) + grid.offset

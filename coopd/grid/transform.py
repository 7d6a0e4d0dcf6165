"""Moving a grid into another frame by a rigid transform (rotation + translation).

Resampling is by inverse mapping: every target cell looks up the source cell under its centre,
so the result has no holes; target cells whose centre falls on unknown (or outside) stay unknown.
"""

import numpy as np

from ..geometry import apply, check_rigid
from . import kernels
from .cells import OCCUPIED_THRESHOLD
from .fusion import empty_like_box
from .grid import OccupancyGrid


def transformed_key_box(grid: OccupancyGrid, t: np.ndarray):
    """Inclusive key box, in the target frame, that holds grid's known cells moved by t."""
    bounds = grid.known_key_bounds()
    if bounds is None:
        return None
    lo, hi = (b.astype(np.float64) for b in bounds)
    corners = np.array([[x, y, z] for x in (lo[0] - 0.5, hi[0] + 0.5)
                        for y in (lo[1] - 0.5, hi[1] + 0.5) for z in (lo[2] - 0.5, hi[2] + 0.5)])
    moved = apply(t, corners * grid.resolution) / grid.resolution
    lo_key = np.floor(moved.min(axis=0) + 0.5).astype(np.int64)
    return lo_key, np.floor(moved.max(axis=0) + 0.5).astype(np.int64)


def _key_space_inverse(t: np.ndarray, resolution: float):
    """(R^T, -R^T t / res): carries a target key to a (fractional) source key."""
    r_inv = t[:3, :3].T.copy()
    return r_inv, -(r_inv @ t[:3, 3]) / resolution


def transform_grid(grid: OccupancyGrid, t) -> OccupancyGrid:
    """A new grid holding `grid` moved by the 4x4 transform t (points p -> R p + t, metres)."""
    t = check_rigid(t)
    box = transformed_key_box(grid, t)
    if box is None:
        return OccupancyGrid.empty((1, 1, 1), grid.resolution, grid.growth)
    out = empty_like_box(box[0], box[1], grid.resolution, grid.growth)
    r_inv, t_inv = _key_space_inverse(t, grid.resolution)
    kernels.resample_into(out.cells, out.offset, grid.cells, grid.offset, r_inv, t_inv, False, 0)
    return out


def fuse_transformed(dst: OccupancyGrid, src: OccupancyGrid, t,
                     threshold: int = OCCUPIED_THRESHOLD) -> int:
    """Fuse src, moved by t into dst's frame, into dst (Table 3) without an intermediate grid.

    dst grows to hold the moved cells. Returns how many dst cells received a known value.
    """
    dst._check_same_resolution(src)
    t = check_rigid(t)
    box = transformed_key_box(src, t)
    if box is None:
        return 0
    dst.ensure(box[0], box[1])
    r_inv, t_inv = _key_space_inverse(t, src.resolution)
    return int(kernels.resample_into(dst.block(box[0], box[1]), box[0], src.cells, src.offset,
                                     r_inv, t_inv, True, threshold))

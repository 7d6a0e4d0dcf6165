"""The 3D dynamic occupancy grid: the data structure every stage of coopd reads and writes."""

from .cells import (
    INACCESSIBLE,
    OCCUPIED_THRESHOLD,
    P_MAX,
    P_MIN,
    P_PRIOR,
    UNKNOWN,
    free_mask,
    known_mask,
    occupied_mask,
)
from .fusion import fuse, fuse_into, fuse_values
from .grid import CellCounts, GridTooLarge, GrowthPolicy, OccupancyGrid
from .resample import resample
from .transform import fuse_transformed, transform_grid

__all__ = [
    "INACCESSIBLE", "OCCUPIED_THRESHOLD", "P_MAX", "P_MIN", "P_PRIOR", "UNKNOWN",
    "CellCounts", "GridTooLarge", "GrowthPolicy", "OccupancyGrid",
    "free_mask", "known_mask", "occupied_mask",
    "fuse", "fuse_into", "fuse_values", "fuse_transformed", "resample", "transform_grid",
]

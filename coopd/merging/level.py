"""Levelling: the small roll/pitch that makes a map's horizontal surfaces horizontal.

Drones share gravity through their IMUs, but a map's frame may still be tilted by a few degrees.
Floors, ceilings and table tops (occupied cells with free space straight above or below) are
parallel planes; the tilt that stacks them into the sharpest height histogram levels the map, so the
gravity-aligned search then only has yaw and translation left to find.
"""

import numba as nb
import numpy as np

from ..geometry import euler_to_matrix, rigid
from ..grid import OccupancyGrid

_JIT = {"nogil": True, "cache": True}


@nb.njit(**_JIT)
def _surface_cells(cells, threshold):
    """Array indices (k, 3) of occupied cells with a free cell straight above or below."""
    mx, my, mz = cells.shape
    out = np.empty((1024, 3), dtype=np.int64)
    n = 0
    for x in range(mx):
        for y in range(my):
            for z in range(mz):
                if cells[x, y, z] < threshold:
                    continue
                above = z + 1 < mz and 0 <= cells[x, y, z + 1] < threshold
                below = z > 0 and 0 <= cells[x, y, z - 1] < threshold
                if above or below:
                    if n == out.shape[0]:
                        grown = np.empty((2 * n, 3), dtype=np.int64)
                        grown[:n] = out
                        out = grown
                    out[n, 0], out[n, 1], out[n, 2] = x, y, z
                    n += 1
    return out[:n]


def horizontal_surface_points(grid: OccupancyGrid, threshold: int, max_points: int = 12000) -> np.ndarray:
    """Centres (metres) of occupied cells with a free cell straight above or below."""
    pts = (_surface_cells(grid.cells, threshold) + grid.offset) * grid.resolution
    return pts[:: max(1, len(pts) // max_points)]


def _sharpness(pts: np.ndarray, roll: float, pitch: float, bin_m: float) -> float:
    r = euler_to_matrix(roll, pitch, 0.0)
    z = pts @ r[2]
    h = np.bincount(np.floor((z - z.min()) / bin_m).astype(np.int64))
    return float(np.sum(h.astype(np.float64) ** 2))


def level_transform(grid: OccupancyGrid, threshold: int, max_tilt_deg: float = 5.0,
                    bin_m: float = 0.05, min_tilt_deg: float = 0.3) -> np.ndarray:
    """4x4 rotation (about the map origin) that levels the map: coarse 1-degree grid, then 0.25.
    Identity when the tilt found is below min_tilt_deg (an IMU-aligned map needs no resampling)."""
    pts = horizontal_surface_points(grid, threshold)
    if len(pts) < 100:
        return np.eye(4)
    best = (0.0, 0.0)
    for step, span in ((1.0, max_tilt_deg), (0.25, 1.0)):
        offsets = np.radians(np.arange(-span, span + 1e-9, step))
        cands = [(best[0] + a, best[1] + b) for a in offsets for b in offsets]
        scores = [_sharpness(pts, a, b, bin_m) for a, b in cands]
        best = cands[int(np.argmax(scores))]
    if np.hypot(*best) < np.radians(min_tilt_deg):
        return np.eye(4)
    return rigid(euler_to_matrix(best[0], best[1], 0.0))

"""Levelling: the small roll/pitch that makes a map's horizontal surfaces horizontal.

Drones share gravity through their IMUs, but a map's frame may still be tilted by a few degrees.
Floors, ceilings and table tops (occupied cells with free space straight above or below) are
parallel planes; the tilt that stacks them into the sharpest height histogram levels the map, so the
gravity-aligned search then only has yaw and translation left to find.
"""

import numba as nb
import numpy as np

from coopd.kernel_cache import CACHE as KERNEL_CACHE

from ..geometry import euler_to_matrix, rigid
from ..grid import OccupancyGrid

_JIT = {"nogil": True, "cache": KERNEL_CACHE}


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


def _rotation_onto_z(n: np.ndarray) -> np.ndarray:
    """Smallest rotation carrying the unit vector n onto +z (Rodrigues; no yaw component)."""
    z = np.array([0.0, 0.0, 1.0])
    axis = np.cross(n, z)
    s, c = float(np.linalg.norm(axis)), float(n @ z)
    if s < 1e-12:
        return np.eye(3)
    k = axis / s
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + s * kx + (1 - c) * kx @ kx


def _fit_parallel_planes(pts: np.ndarray, r0: np.ndarray, band_m: float, layers: int = 2) -> np.ndarray:
    """Common normal of the most populated horizontal layers (after turning by r0), by least squares
    z = a x + b y + c_k with one intercept per layer."""
    z = pts @ r0[2]
    h = np.bincount(np.floor((z - z.min()) / band_m).astype(np.int64))
    peaks = []
    for i in np.argsort(h)[::-1]:
        if all(abs(int(i) - j) * band_m > 0.5 for j in peaks):
            peaks.append(int(i))
        if len(peaks) == layers:
            break
    cols, rows_z = [], []
    for k, i in enumerate(peaks):
        centre = z.min() + (i + 0.5) * band_m
        sel = np.abs(z - centre) <= 1.5 * band_m
        if sel.sum() < 30:
            continue
        block = np.zeros((int(sel.sum()), 2 + len(peaks)))
        block[:, 0], block[:, 1], block[:, 2 + k] = pts[sel, 0], pts[sel, 1], 1.0
        cols.append(block)
        rows_z.append(pts[sel, 2])
    if not cols:
        return r0[2]
    a = np.concatenate(cols)
    sol, *_ = np.linalg.lstsq(a, np.concatenate(rows_z), rcond=None)
    n = np.array([-sol[0], -sol[1], 1.0])
    return n / np.linalg.norm(n)


def level_transform(grid: OccupancyGrid, threshold: int, max_tilt_deg: float = 5.0,
                    bin_m: float = 0.05, min_tilt_deg: float = 0.3) -> np.ndarray:
    """4x4 rotation (about the map origin) that levels the map: the sharpest height histogram over a
    1-degree grid of tilts, then a least-squares fit of the two most populated horizontal layers
    (floor and ceiling) with a shared normal. Identity when the tilt found is below min_tilt_deg (an
    IMU-aligned map needs no resampling)."""
    pts = horizontal_surface_points(grid, threshold)
    if len(pts) < 100:
        return np.eye(4)
    offsets = np.radians(np.arange(-max_tilt_deg, max_tilt_deg + 1e-9, 1.0))
    cands = [(a, b) for a in offsets for b in offsets]
    scores = [_sharpness(pts, a, b, bin_m) for a, b in cands]
    r = euler_to_matrix(*cands[int(np.argmax(scores))], 0.0)
    for _ in range(2):
        n = _fit_parallel_planes(pts, r, 2 * grid.resolution)
        r = _rotation_onto_z(n)
    if np.degrees(np.arccos(np.clip(r[2, 2], -1.0, 1.0))) < min_tilt_deg:
        return np.eye(4)
    return rigid(r)

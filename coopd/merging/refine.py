"""Refinement of a transform on the full-resolution grids: ICP between occupied cell centres, then a
sub-cell shift on a smoothed surface.

Point-to-point ICP with a shrinking correspondence radius (from six cells down to 1.5, then held),
6 DoF so that small roll/pitch differences between drones are absorbed. Between two lattices of cell
centres it has a local minimum at every whole-cell slide along a wall (every wall cell finds a
partner at distance 0; only edges pull back), so it can stop a cell away from the truth even on a
lossless copy. `subcell_shift` then moves the result by the translation, within +-1 cell in quarter
cells, that puts the moved points highest on a Gaussian-smoothed image of the target's occupied
cells, where sliding along a wall changes nothing and edges and corners decide.
"""

from dataclasses import dataclass

import numba as nb
import numpy as np

from coopd.kernel_cache import CACHE as KERNEL_CACHE

from ..geometry import apply
from .mtm import estimate
from .preprocess import gaussian

_JIT = {"nogil": True, "cache": KERNEL_CACHE}
SUBCELL_STEPS = np.arange(-4, 5) / 4.0
"""Shifts tried per axis by subcell_shift, in cells."""


@nb.njit(**_JIT)
def _nearest_cells(occupied, offset, points, inv_res, max_cells, out_idx, out_dist):
    """Nearest occupied cell of each point (cell-index units) within max_cells, searched in shells of
    growing Chebyshev radius around the point's cell until no farther shell can hold a nearer one."""
    mx, my, mz = occupied.shape
    for p in range(points.shape[0]):
        kx = points[p, 0] * inv_res - offset[0]
        ky = points[p, 1] * inv_res - offset[1]
        kz = points[p, 2] * inv_res - offset[2]
        cx, cy, cz = int(np.floor(kx + 0.5)), int(np.floor(ky + 0.5)), int(np.floor(kz + 0.5))
        best = np.inf
        bx = by = bz = -1
        s = 0
        while True:
            bound = max(0.0, s - 0.5)  # the point lies within half a cell of its cell's centre
            if bound > max_cells or bound * bound >= best:
                break
            for dx in range(-s, s + 1):
                x = cx + dx
                if x < 0 or x >= mx:
                    continue
                for dy in range(-s, s + 1):
                    y = cy + dy
                    if y < 0 or y >= my:
                        continue
                    edge = dx == -s or dx == s or dy == -s or dy == s
                    step = 1 if edge else max(1, 2 * s)
                    for dz in range(-s, s + 1, step):
                        z = cz + dz
                        if z < 0 or z >= mz or not occupied[x, y, z]:
                            continue
                        d = (x - kx) ** 2 + (y - ky) ** 2 + (z - kz) ** 2
                        if d < best:
                            best, bx, by, bz = d, x, y, z
            s += 1
        if best <= max_cells * max_cells:
            out_dist[p] = np.sqrt(best)
            out_idx[p, 0], out_idx[p, 1], out_idx[p, 2] = bx, by, bz
        else:
            out_dist[p] = np.inf


@dataclass(frozen=True)
class OccupiedCells:
    """A grid's occupied cells for nearest-neighbour queries: ICP's target. Cell centres lie on a
    lattice, so the nearest one is found by visiting the cells around a point, nearest shell first; a
    k-d tree over a lattice is slow (every query meets many equidistant points)."""

    occupied: np.ndarray
    offset: np.ndarray
    resolution: float

    def nearest(self, points: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray]:
        """(within, centres): which points have an occupied cell centre within radius (metres), and
        the nearest such centre of each (rows of the others are undefined)."""
        points = np.ascontiguousarray(points, dtype=np.float64)
        idx = np.empty((len(points), 3), dtype=np.int64)
        dist = np.empty(len(points))
        _nearest_cells(self.occupied, np.asarray(self.offset, dtype=np.int64), points, 1.0 / self.resolution,
                       radius / self.resolution, idx, dist)
        return np.isfinite(dist), (idx + self.offset) * self.resolution


def icp(target: OccupiedCells, source: np.ndarray, t0: np.ndarray, iterations: int,
        yaw_only: bool = False) -> tuple[np.ndarray, float]:
    """(refined T, inlier fraction): source points (b frame) pulled onto the target's occupied cell
    centres (a frame)."""
    t = np.asarray(t0, dtype=np.float64).copy()
    coarse = max(1, iterations // 2)
    held = np.full(max(0, iterations - coarse), 1.5)
    radii = np.concatenate([np.geomspace(6.0, 1.5, coarse), held]) * target.resolution
    frac = 0.0
    previous = None
    for k, r in enumerate(radii):
        ok, nearest = target.nearest(apply(t, source), r)
        frac = float(ok.mean()) if len(ok) else 0.0
        if ok.sum() < 10:
            break
        pairs = np.where(ok[:, None], nearest, np.nan)
        if previous is not None and np.array_equal(pairs, previous, equal_nan=True):
            if k >= coarse:  # same pairs under the held radius: every further step repeats this one
                break
            continue  # same pairs, same estimate
        previous = pairs
        t = estimate(source[ok], nearest[ok], yaw_only)
    return t, frac


@nb.njit(**_JIT)
def _shift_scores(field, keys, steps):
    """Sum of the trilinearly interpolated field at keys (fractional cell indices) + each shift."""
    mx, my, mz = field.shape
    n = steps.shape[0]
    out = np.zeros((n, n, n))
    for i in range(n):
        for j in range(n):
            for k in range(n):
                acc = 0.0
                for p in range(keys.shape[0]):
                    x = keys[p, 0] + steps[i]
                    y = keys[p, 1] + steps[j]
                    z = keys[p, 2] + steps[k]
                    x0, y0, z0 = int(np.floor(x)), int(np.floor(y)), int(np.floor(z))
                    if x0 < 0 or y0 < 0 or z0 < 0 or x0 + 1 >= mx or y0 + 1 >= my or z0 + 1 >= mz:
                        continue
                    fx, fy, fz = x - x0, y - y0, z - z0
                    for a in range(2):
                        wa = fx if a else 1.0 - fx
                        for b in range(2):
                            wb = fy if b else 1.0 - fy
                            for c in range(2):
                                wc = fz if c else 1.0 - fz
                                acc += wa * wb * wc * field[x0 + a, y0 + b, z0 + c]
                out[i, j, k] = acc
    return out


def subcell_shift(target_occupied: np.ndarray, target_offset: np.ndarray, resolution: float,
                  source: np.ndarray, t: np.ndarray) -> np.ndarray:
    """t moved by the translation (within +-1 cell, quarter-cell steps) that lays the source points
    (b frame, metres) highest on the target's occupied cells smoothed by a Gaussian of one cell."""
    keys = apply(t, source) / resolution - target_offset
    lo = np.maximum(np.floor(keys.min(axis=0)).astype(np.int64) - 4, 0)
    hi = np.minimum(np.ceil(keys.max(axis=0)).astype(np.int64) + 5, np.array(target_occupied.shape))
    if len(source) == 0 or np.any(hi - lo < 2):
        return t
    crop = target_occupied[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]].astype(np.float32)
    field = gaussian(crop, radius=2, sigma=1.0)
    scores = _shift_scores(field, np.ascontiguousarray(keys - lo), SUBCELL_STEPS)
    best = np.array(np.unravel_index(int(np.argmax(scores)), scores.shape))
    out = t.copy()
    out[:3, 3] += SUBCELL_STEPS[best] * resolution
    return out

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

import numba as nb
import numpy as np
from scipy.spatial import cKDTree

from ..geometry import apply
from .mtm import estimate
from .preprocess import gaussian

_JIT = {"nogil": True, "cache": True}
SUBCELL_STEPS = np.arange(-4, 5) / 4.0
"""Shifts tried per axis by subcell_shift, in cells."""


def icp(tree: cKDTree, target: np.ndarray, source: np.ndarray, t0: np.ndarray, iterations: int,
        resolution: float, yaw_only: bool = False) -> tuple[np.ndarray, float]:
    """(refined T, inlier fraction): source points (b frame) pulled onto the tree's points (a frame)."""
    t = np.asarray(t0, dtype=np.float64).copy()
    coarse = max(1, iterations // 2)
    held = np.full(max(0, iterations - coarse), 1.5)
    radii = np.concatenate([np.geomspace(6.0, 1.5, coarse), held]) * resolution
    frac = 0.0
    for r in radii:
        moved = apply(t, source)
        d, j = tree.query(moved, distance_upper_bound=r)
        ok = np.isfinite(d)
        frac = float(ok.mean()) if len(ok) else 0.0
        if ok.sum() < 10:
            break
        t = estimate(source[ok], target[j[ok]], yaw_only)
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

"""Refinement of a transform on the full-resolution grids: ICP between occupied cell centres.

Point-to-point ICP with a shrinking correspondence radius (from six cells down to 1.5, then held),
6 DoF so that small roll/pitch differences between drones are absorbed.
"""

import numpy as np
from scipy.spatial import cKDTree

from ..geometry import apply
from .mtm import estimate


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

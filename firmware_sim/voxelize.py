"""Ground-truth occupancy grids: voxelise a world's primitives analytically on a regular grid."""

from __future__ import annotations

import math

import numpy as np

from firmware_sim.shapes import Shape


def grid_frame(bounds_min, bounds_max, resolution: float) -> tuple[np.ndarray, tuple[int, int, int]]:
    """Return (origin of cell [0,0,0]'s centre, grid shape) for cells aligned to multiples of resolution."""
    lo = np.floor(np.asarray(bounds_min, float) / resolution + 1e-9) * resolution
    hi = np.ceil(np.asarray(bounds_max, float) / resolution - 1e-9) * resolution
    shape = tuple(max(1, int(round((h - l) / resolution))) for l, h in zip(lo, hi, strict=True))
    return lo + resolution / 2.0, shape


def voxelize(shapes: list[Shape], bounds_min, bounds_max, resolution: float) -> tuple[np.ndarray, np.ndarray]:
    """Mark every cell sharing volume with a shape; returns (occ[x, y, z] bool, centre of cell [0,0,0])."""
    if not (resolution > 0 and math.isfinite(resolution)):
        raise ValueError(f"resolution must be a positive number, got {resolution!r}")
    origin, shape = grid_frame(bounds_min, bounds_max, resolution)
    occ = np.zeros(shape, dtype=bool)
    corner = origin - resolution / 2.0
    for s in shapes:
        smin, smax = s.bounds()
        i0 = np.clip(np.floor((smin - corner) / resolution).astype(int), 0, np.array(shape))
        i1 = np.clip(np.ceil((smax - corner) / resolution).astype(int), 0, np.array(shape))
        if np.any(i1 <= i0):
            continue
        axes = [corner[k] + resolution * np.arange(i0[k], i1[k]) for k in range(3)]
        gx, gy, gz = np.meshgrid(*axes, indexing="ij")
        lo = np.stack([gx, gy, gz], axis=-1)
        hit = s.overlaps_cells(lo, lo + resolution)
        occ[i0[0] : i1[0], i0[1] : i1[1], i0[2] : i1[2]] |= hit
    return occ, origin

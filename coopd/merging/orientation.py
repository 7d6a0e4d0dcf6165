"""Keypoint orientation (§8.4): a potential field relaxed by Gauss–Seidel, angles by eq. 20.

The field starts as the intensity image; cells at or above the occupied intensity are obstacles held
fixed, every other cell relaxes towards the mean of its six neighbours (harmonic potential, as in
potential-field exploration). 'global' relaxes the whole map once; 'local' relaxes a cube of radius
KP_r around each keypoint only.
"""

import numba as nb
import numpy as np

from .params import MergeParams

_JIT = {"nogil": True, "cache": True}


@nb.njit(**_JIT)
def _at(f, x, y, z):
    mx, my, mz = f.shape
    if 0 <= x < mx and 0 <= y < my and 0 <= z < mz:
        return f[x, y, z]
    return 0.0


@nb.njit(**_JIT)
def gauss_seidel(field, fixed_level, iterations, lo, hi):
    """In-place Gauss–Seidel sweeps of Laplace's equation on the box lo..hi (exclusive hi)."""
    for _ in range(iterations):
        for x in range(lo[0], hi[0]):
            for y in range(lo[1], hi[1]):
                for z in range(lo[2], hi[2]):
                    if field[x, y, z] >= fixed_level:
                        continue
                    field[x, y, z] = (_at(field, x - 1, y, z) + _at(field, x + 1, y, z)
                                      + _at(field, x, y - 1, z) + _at(field, x, y + 1, z)
                                      + _at(field, x, y, z - 1) + _at(field, x, y, z + 1)) / 6.0


@nb.njit(**_JIT)
def euler_from_field(g, x, y, z):
    """Eq. 20: (alpha, beta, gamma) from central differences of the field at (x, y, z)."""
    dx = _at(g, x - 1, y, z) - _at(g, x + 1, y, z)
    dy = _at(g, x, y - 1, z) - _at(g, x, y + 1, z)
    dz = _at(g, x, y, z - 1) - _at(g, x, y, z + 1)
    return np.arctan2(dz, dy), np.arctan2(dx, dz), np.arctan2(dy, dx)


@nb.njit(**_JIT)
def _orient_global(field, keypoints, fixed_level, iterations):
    n = keypoints.shape[0]
    lo = np.zeros(3, dtype=np.int64)
    hi = np.array(field.shape, dtype=np.int64)
    gauss_seidel(field, fixed_level, iterations, lo, hi)
    out = np.empty((n, 3))
    for p in range(n):
        a, b, c = euler_from_field(field, keypoints[p, 0], keypoints[p, 1], keypoints[p, 2])
        out[p, 0], out[p, 1], out[p, 2] = a, b, c
    return out


@nb.njit(**_JIT)
def _orient_local(img, keypoints, fixed_level, iterations, radius):
    n = keypoints.shape[0]
    out = np.empty((n, 3))
    w = 2 * radius + 3
    for p in range(n):
        cx, cy, cz = keypoints[p, 0], keypoints[p, 1], keypoints[p, 2]
        cube = np.empty((w, w, w))
        for a in range(w):
            for b in range(w):
                for c in range(w):
                    cube[a, b, c] = _at(img, cx - radius - 1 + a, cy - radius - 1 + b, cz - radius - 1 + c)
        lo = np.ones(3, dtype=np.int64)
        hi = np.full(3, w - 1, dtype=np.int64)
        gauss_seidel(cube, fixed_level, iterations, lo, hi)
        a, b, c = euler_from_field(cube, radius + 1, radius + 1, radius + 1)
        out[p, 0], out[p, 1], out[p, 2] = a, b, c
    return out


def orientations(img: np.ndarray, keypoints: np.ndarray, params: MergeParams) -> np.ndarray:
    """(k, 3) Euler angles (roll alpha, pitch beta, yaw gamma) of each keypoint, radians."""
    fixed = float(params.occupied_threshold) * 2.55
    kp = np.ascontiguousarray(keypoints, dtype=np.int64)
    if len(kp) == 0:
        return np.empty((0, 3))
    if params.orientation_mode == "global":
        return _orient_global(img.astype(np.float64), kp, fixed, params.gauss_seidel_iterations)
    if params.orientation_mode == "local":
        return _orient_local(img.astype(np.float64), kp, fixed, params.gauss_seidel_iterations,
                             params.orientation_radius)
    raise ValueError(f"orientation_mode must be 'global' or 'local', not {params.orientation_mode!r}")

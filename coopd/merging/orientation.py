"""Keypoint orientation (§8.4): a potential field relaxed from the intensity image, angles by eq. 20.

The field starts as the intensity image; cells at or above the occupied intensity are obstacles held
fixed, every other cell relaxes towards the mean of its six neighbours (harmonic potential, as in
potential-field exploration). 'global' relaxes the whole map once; 'local' relaxes a cube of radius
KP_r around each keypoint only.

Two choices make the orientation follow a yaw turn of the map (tests/merging/test_orientation.py
turns a map through 0-360 degrees in 15 degree steps):
- `orientation_solver`: 'jacobi' updates every cell from the previous sweep, so the field does not
  depend on the order cells are visited; the thesis' in-place Gauss-Seidel ('gauss_seidel')
  propagates further along the sweep direction in its few iterations, which a turn of the map changes.
- `orientation_window`: the gradient is averaged over a Gaussian-weighted ball of this radius (cells)
  around the keypoint instead of read by one central difference, so the resampling of a map turned by
  an arbitrary angle moves the angle little. 0 reads the single central difference of eq. 20.
"""

import numba as nb
import numpy as np

from coopd.kernel_cache import CACHE as KERNEL_CACHE

from .params import MergeParams

_JIT = {"nogil": True, "cache": KERNEL_CACHE}
SOLVERS = {"gauss_seidel": 0, "jacobi": 1}


@nb.njit(**_JIT)
def _at(f, x, y, z):
    mx, my, mz = f.shape
    if 0 <= x < mx and 0 <= y < my and 0 <= z < mz:
        return f[x, y, z]
    return 0.0


@nb.njit(**_JIT)
def relax(field, fixed_level, iterations, lo, hi, solver):
    """In-place sweeps of Laplace's equation on the box lo..hi (exclusive hi), which must leave a
    one-cell border of the field untouched (the caller pads); cells at or above fixed_level stay.
    solver 0: Gauss-Seidel (in place), 1: Jacobi (from the previous sweep)."""
    prev = field.copy() if solver == 1 else field
    for _ in range(iterations):
        if solver == 1:
            prev[:] = field
        for x in range(lo[0], hi[0]):
            for y in range(lo[1], hi[1]):
                for z in range(lo[2], hi[2]):
                    if field[x, y, z] >= fixed_level:
                        continue
                    field[x, y, z] = (prev[x - 1, y, z] + prev[x + 1, y, z] + prev[x, y - 1, z]
                                      + prev[x, y + 1, z] + prev[x, y, z - 1] + prev[x, y, z + 1]) / 6.0


@nb.njit(**_JIT)
def _gradient(g, x, y, z, window):
    """Downhill gradient of the field at (x, y, z): central differences, Gaussian-averaged over a ball
    of radius window (sigma = window / 2; window 0: the single central difference of eq. 20)."""
    dx = dy = dz = 0.0
    inv = 2.0 / (window * window) if window > 0 else 0.0
    for a in range(-window, window + 1):
        for b in range(-window, window + 1):
            for c in range(-window, window + 1):
                r2 = a * a + b * b + c * c
                if r2 > window * window:
                    continue
                w = np.exp(-r2 * inv)
                px, py, pz = x + a, y + b, z + c
                dx += w * (_at(g, px - 1, py, pz) - _at(g, px + 1, py, pz))
                dy += w * (_at(g, px, py - 1, pz) - _at(g, px, py + 1, pz))
                dz += w * (_at(g, px, py, pz - 1) - _at(g, px, py, pz + 1))
    return dx, dy, dz


@nb.njit(**_JIT)
def euler_from_field(g, x, y, z, window):
    """Eq. 20: (alpha, beta, gamma) from the (averaged) gradient of the field at (x, y, z)."""
    dx, dy, dz = _gradient(g, x, y, z, window)
    return np.arctan2(dz, dy), np.arctan2(dx, dz), np.arctan2(dy, dx)


@nb.njit(**_JIT)
def _orient_global(img, keypoints, fixed_level, iterations, solver, window):
    n = keypoints.shape[0]
    mx, my, mz = img.shape
    field = np.zeros((mx + 2, my + 2, mz + 2))  # outside the map reads 0
    field[1:-1, 1:-1, 1:-1] = img
    lo = np.ones(3, dtype=np.int64)
    hi = np.array([mx + 1, my + 1, mz + 1], dtype=np.int64)
    relax(field, fixed_level, iterations, lo, hi, solver)
    out = np.empty((n, 3))
    for p in range(n):
        x, y, z = keypoints[p, 0] + 1, keypoints[p, 1] + 1, keypoints[p, 2] + 1
        a, b, c = euler_from_field(field, x, y, z, window)
        out[p, 0], out[p, 1], out[p, 2] = a, b, c
    return out


@nb.njit(**_JIT)
def _orient_local(img, keypoints, fixed_level, iterations, radius, solver, window):
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
        relax(cube, fixed_level, iterations, lo, hi, solver)
        a, b, c = euler_from_field(cube, radius + 1, radius + 1, radius + 1, min(window, radius))
        out[p, 0], out[p, 1], out[p, 2] = a, b, c
    return out


def orientations(img: np.ndarray, keypoints: np.ndarray, params: MergeParams) -> np.ndarray:
    """(k, 3) Euler angles (roll alpha, pitch beta, yaw gamma) of each keypoint, radians."""
    fixed = float(params.occupied_threshold) * 2.55
    kp = np.ascontiguousarray(keypoints, dtype=np.int64)
    solver = SOLVERS.get(params.orientation_solver)
    if solver is None:
        raise ValueError(f"orientation_solver must be one of {sorted(SOLVERS)}, "
                         f"not {params.orientation_solver!r}")
    sweeps, window = params.gauss_seidel_iterations, int(params.orientation_window)
    if len(kp) == 0:
        return np.empty((0, 3))
    if params.orientation_mode == "global":
        return _orient_global(img.astype(np.float64), kp, fixed, sweeps, solver, window)
    if params.orientation_mode == "local":
        return _orient_local(img.astype(np.float64), kp, fixed, sweeps, params.orientation_radius, solver,
                             window)
    raise ValueError(f"orientation_mode must be 'global' or 'local', not {params.orientation_mode!r}")

"""Eigenvectors of small symmetric matrices by cyclic Jacobi rotations, in nopython loops.

Kabsch's rotation is one eigenvector of a 4 x 4 matrix (Horn's quaternion form). numba's np.linalg
would call LAPACK through SciPy, which the drone install leaves out: 143 MB of site-packages, and
0.3 s of every process start spent importing it (numba imports SciPy's linear algebra at its first
kernel call whenever SciPy is installed).
"""

import numba as nb
import numpy as np

from coopd.kernel_cache import CACHE as KERNEL_CACHE

_JIT = {"nogil": True, "cache": KERNEL_CACHE}

MAX_SWEEPS = 60
"""Jacobi converges quadratically: a 4 x 4 matrix settles within 5 sweeps, a 16 x 16 within 10; the cap
bounds the loop whatever the input."""


@nb.njit(**_JIT)
def symmetric_eigen(a):
    """(values ascending, vectors as columns) of the symmetric matrix a; a itself is not changed.
    Each rotation zeroes one off-diagonal pair; sweeps stop when the off-diagonal mass is below
    machine precision of the whole matrix. Tied values keep the order of their axes; a matrix with
    a NaN or an infinity gives NaN throughout."""
    n = a.shape[0]
    m = a.copy()
    v = np.eye(n)
    if not np.isfinite(m).all():
        return np.full(n, np.nan), np.full((n, n), np.nan)
    big = np.abs(m).max()
    if big > 0.0:
        m /= big  # squares below stay within float range whatever the input's scale
    scale = 0.0
    for p in range(n):
        for q in range(n):
            scale += m[p, q] * m[p, q]
    for _ in range(MAX_SWEEPS):
        off = 0.0
        for p in range(n - 1):
            for q in range(p + 1, n):
                off += m[p, q] * m[p, q]
        if not off > 1e-32 * scale:
            break
        for p in range(n - 1):
            for q in range(p + 1, n):
                apq = m[p, q]
                if apq == 0.0:
                    continue
                theta = (m[q, q] - m[p, p]) / (2.0 * apq)
                t = 1.0 / (abs(theta) + np.sqrt(theta * theta + 1.0))
                if theta < 0.0:
                    t = -t
                c = 1.0 / np.sqrt(t * t + 1.0)
                s = t * c
                for k in range(n):  # m = J^T m J, columns then rows
                    mkp, mkq = m[k, p], m[k, q]
                    m[k, p] = c * mkp - s * mkq
                    m[k, q] = s * mkp + c * mkq
                for k in range(n):
                    mpk, mqk = m[p, k], m[q, k]
                    m[p, k] = c * mpk - s * mqk
                    m[q, k] = s * mpk + c * mqk
                for k in range(n):
                    vkp, vkq = v[k, p], v[k, q]
                    v[k, p] = c * vkp - s * vkq
                    v[k, q] = s * vkp + c * vkq
    values = np.empty(n)
    for k in range(n):
        values[k] = m[k, k] * big
    order = np.argsort(values, kind="mergesort")  # stable: tied values keep the input's order
    return values[order], v[:, order].copy()

"""Map Transformation Matrix (§8.8): Kabsch (a proper rotation, as the reflection fix gives), a yaw-only
variant, eq. 33.

Points are in metres of each map's own frame (keypoint indices converted with FeatureImage.to_metres
before estimating), which is the full-resolution correction of eq. 34 done up front.
"""

import numba as nb
import numpy as np

from coopd.kernel_cache import CACHE as KERNEL_CACHE

from .eigen import symmetric_eigen

_JIT = {"nogil": True, "cache": KERNEL_CACHE}


@nb.njit(**_JIT)
def kabsch(src, dst):
    """4x4 rigid T minimising sum |dst - T src|^2 (eqs. 25-32). The rotation is that of the SVD with
    the reflection fix, computed in Horn's quaternion form: the unit quaternion is the eigenvector of
    the largest eigenvalue of a 4x4 matrix built from the cross-covariance, so it is always a proper
    rotation (no reflection to fix) and needs no LAPACK."""
    cs = np.zeros(3)
    cd = np.zeros(3)
    n = src.shape[0]
    for i in range(n):
        cs += src[i]
        cd += dst[i]
    cs /= n
    cd /= n
    h = np.zeros((3, 3))
    for i in range(n):
        for r in range(3):
            a = src[i, r] - cs[r]
            for c in range(3):
                h[r, c] += a * (dst[i, c] - cd[c])
    sxx, sxy, sxz = h[0, 0], h[0, 1], h[0, 2]
    syx, syy, syz = h[1, 0], h[1, 1], h[1, 2]
    szx, szy, szz = h[2, 0], h[2, 1], h[2, 2]
    k = np.array([[sxx + syy + szz, syz - szy, szx - sxz, sxy - syx],
                  [syz - szy, sxx - syy - szz, sxy + syx, szx + sxz],
                  [szx - sxz, sxy + syx, -sxx + syy - szz, syz + szy],
                  [sxy - syx, szx + sxz, syz + szy, -sxx - syy + szz]])
    values, vectors = symmetric_eigen(k)
    q = vectors[:, np.argmax(values)]  # the first of tied maxima: no information gives no turn
    t = np.eye(4)
    t[:3, :3] = quaternion_matrix(q[0], q[1], q[2], q[3])
    for r in range(3):
        t[r, 3] = cd[r] - (t[r, 0] * cs[0] + t[r, 1] * cs[1] + t[r, 2] * cs[2])
    return t


@nb.njit(**_JIT)
def quaternion_matrix(w, x, y, z):
    """3x3 rotation of the unit quaternion (w, x, y, z)."""
    r = np.empty((3, 3))
    r[0, 0] = w * w + x * x - y * y - z * z
    r[0, 1] = 2.0 * (x * y - w * z)
    r[0, 2] = 2.0 * (x * z + w * y)
    r[1, 0] = 2.0 * (x * y + w * z)
    r[1, 1] = w * w - x * x + y * y - z * z
    r[1, 2] = 2.0 * (y * z - w * x)
    r[2, 0] = 2.0 * (x * z - w * y)
    r[2, 1] = 2.0 * (y * z + w * x)
    r[2, 2] = w * w - x * x - y * y + z * z
    return r


@nb.njit(**_JIT)
def kabsch_yaw(src, dst):
    """4x4 T = (Rz(yaw), t) minimising sum |dst - T src|^2: roll and pitch held at zero."""
    n = src.shape[0]
    cs = np.zeros(3)
    cd = np.zeros(3)
    for i in range(n):
        cs += src[i]
        cd += dst[i]
    cs /= n
    cd /= n
    sn = 0.0
    cn = 0.0
    for i in range(n):
        ax, ay = src[i, 0] - cs[0], src[i, 1] - cs[1]
        bx, by = dst[i, 0] - cd[0], dst[i, 1] - cd[1]
        sn += ax * by - ay * bx
        cn += ax * bx + ay * by
    yaw = np.arctan2(sn, cn)
    c, s = np.cos(yaw), np.sin(yaw)
    t = np.eye(4)
    t[0, 0], t[0, 1], t[1, 0], t[1, 1] = c, -s, s, c
    t[0, 3] = cd[0] - (c * cs[0] - s * cs[1])
    t[1, 3] = cd[1] - (s * cs[0] + c * cs[1])
    t[2, 3] = cd[2] - cs[2]
    return t


def estimate(src: np.ndarray, dst: np.ndarray, yaw_only: bool) -> np.ndarray:
    """Rigid transform carrying src points onto dst points (yaw + translation when yaw_only)."""
    src = np.ascontiguousarray(src, dtype=np.float64)
    dst = np.ascontiguousarray(dst, dtype=np.float64)
    return kabsch_yaw(src, dst) if yaw_only else kabsch(src, dst)


def euler_eq33(t: np.ndarray):
    """Eq. 33 read as the usual x-y-z decomposition: (tx, ty, tz, roll, pitch, yaw) of a rigid T."""
    r = t[:3, :3]
    roll = np.arctan2(r[2, 1], r[2, 2])
    pitch = np.arctan2(-r[2, 0], np.hypot(r[2, 1], r[2, 2]))
    yaw = np.arctan2(r[1, 0], r[0, 0])
    return float(t[0, 3]), float(t[1, 3]), float(t[2, 3]), float(roll), float(pitch), float(yaw)

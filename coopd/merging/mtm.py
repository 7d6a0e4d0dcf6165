"""Map Transformation Matrix (§8.8): Kabsch with the reflection fix, a yaw-only variant, eq. 33.

Points are in metres of each map's own frame (keypoint indices converted with FeatureImage.to_metres
before estimating), which is the full-resolution correction of eq. 34 done up front.
"""

import numba as nb
import numpy as np

from coopd.kernel_cache import CACHE as KERNEL_CACHE

_JIT = {"nogil": True, "cache": KERNEL_CACHE}


@nb.njit(**_JIT)
def kabsch(src, dst):
    """4x4 rigid T minimising sum |dst - T src|^2 (eqs. 25-32; det < 0 flips V's last column)."""
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
    u, _, vt = np.linalg.svd(h)
    v = vt.T.copy()
    r = v @ u.T
    if np.linalg.det(r) < 0:
        v[:, 2] *= -1.0
        r = v @ u.T
    t = np.eye(4)
    t[:3, :3] = r
    t[:3, 3] = cd - r @ cs
    return t


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
    t[:3, 3] = cd - t[:3, :3] @ cs
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

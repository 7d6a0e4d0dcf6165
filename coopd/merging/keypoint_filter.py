"""Keypoint filtering (§8.3): score V (eq. 19) and non-maximum suppression within KF_ar."""

import numba as nb
import numpy as np

from coopd.kernel_cache import CACHE as KERNEL_CACHE

from .params import MergeParams

_JIT = {"nogil": True, "cache": KERNEL_CACHE}


@nb.njit(**_JIT)
def score_v(img, keypoints, radius):
    """Eq. 19: sum of |m_xyz - m_ijk| over the cube of radius KF_r (outside the image reads 0)."""
    mx, my, mz = img.shape
    out = np.empty(keypoints.shape[0])
    for p in range(keypoints.shape[0]):
        x, y, z = keypoints[p, 0], keypoints[p, 1], keypoints[p, 2]
        c = img[x, y, z]
        acc = 0.0
        for a in range(x - radius, x + radius + 1):
            for b in range(y - radius, y + radius + 1):
                for d in range(z - radius, z + radius + 1):
                    v = img[a, b, d] if (0 <= a < mx and 0 <= b < my and 0 <= d < mz) else 0.0
                    acc += abs(c - v)
        out[p] = acc
    return out


@nb.njit(**_JIT)
def suppress(shape, keypoints, scores, radius):
    """True for keypoints whose score beats every other keypoint within Euclidean radius (cells)."""
    slot = np.full((shape[0], shape[1], shape[2]), -1, dtype=np.int64)
    for p in range(keypoints.shape[0]):
        slot[keypoints[p, 0], keypoints[p, 1], keypoints[p, 2]] = p
    r = int(np.floor(radius))
    r2 = radius * radius
    keep = np.ones(keypoints.shape[0], dtype=np.bool_)
    for p in range(keypoints.shape[0]):
        x, y, z = keypoints[p, 0], keypoints[p, 1], keypoints[p, 2]
        for a in range(max(0, x - r), min(shape[0], x + r + 1)):
            for b in range(max(0, y - r), min(shape[1], y + r + 1)):
                for d in range(max(0, z - r), min(shape[2], z + r + 1)):
                    q = slot[a, b, d]
                    if q < 0 or q == p or (a - x) ** 2 + (b - y) ** 2 + (d - z) ** 2 > r2:
                        continue
                    if scores[q] > scores[p] or (scores[q] == scores[p] and q < p):
                        keep[p] = False
    return keep


def filter_keypoints(img: np.ndarray, keypoints: np.ndarray, params: MergeParams):
    """(kept keypoints, their scores): suppressed to local maxima of V, strongest max_keypoints first."""
    if len(keypoints) == 0:
        return keypoints, np.empty(0)
    scores = score_v(img, keypoints, params.filter_score_radius)
    shape = np.array(img.shape, dtype=np.int64)
    keep = suppress(shape, keypoints, scores, float(params.filter_adjacent_radius))
    kp, sc = keypoints[keep], scores[keep]
    order = np.argsort(-sc, kind="stable")[: params.max_keypoints]
    return kp[order], sc[order]

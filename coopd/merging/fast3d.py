"""FAST 3D keypoint detection (§8.2, Algorithms 2 and 3): rFAST on the XY, ZX and YZ planes."""

import numba as nb
import numpy as np
from scipy import ndimage

from .params import MergeParams

_JIT = {"nogil": True, "cache": True}


def circle_mask(radius: int) -> np.ndarray:
    """(dx, dy, 0) offsets of the cells whose distance rounds to radius, ordered by angle (FAST's
    16-cell Bresenham ring for radius 3)."""
    r = np.arange(-radius - 1, radius + 2)
    dx, dy = (v.ravel() for v in np.meshgrid(r, r, indexing="ij"))
    ring = np.abs(np.hypot(dx, dy) - radius) < 0.5
    dx, dy = dx[ring], dy[ring]
    order = np.argsort(np.arctan2(dy, dx), kind="stable")
    return np.stack([dx[order], dy[order], np.zeros(len(order), dtype=dx.dtype)], 1).astype(np.int64)


@nb.njit(**_JIT)
def rfast(ip, ring, s, th, n, sign):
    """Algorithm 3: the rotated cross check, then n contiguous ring cells beyond th (sign +1 brighter)."""
    m = ring.shape[0]
    for i in range(s):
        c = 0
        for q in range(4):
            if sign * (ring[(i + q * s) % m] - ip) > th:
                c += 1
        if c >= 3:
            run = 0
            for j in range(2 * m):
                if sign * (ring[j % m] - ip) > th:
                    run += 1
                    if run >= n:
                        return True
                else:
                    run = 0
            return False
    return False


@nb.njit(**_JIT)
def _nh_mean(img, x, y, z, nr):
    """getCellNhMean: mean of the cube of radius nr around (x, y, z); outside the image reads 0."""
    mx, my, mz = img.shape
    acc = 0.0
    cnt = 0
    for a in range(x - nr, x + nr + 1):
        for b in range(y - nr, y + nr + 1):
            for c in range(z - nr, z + nr + 1):
                cnt += 1
                if 0 <= a < mx and 0 <= b < my and 0 <= c < mz:
                    acc += img[a, b, c]
    return acc / cnt


@nb.njit(**_JIT)
def fast3d_mask(img, known, mask, n, th, nr, both):
    """Algorithm 2: True where a known cell passes rFAST on any of the three planes."""
    mx, my, mz = img.shape
    m = mask.shape[0]
    s = m // 4
    out = np.zeros(img.shape, dtype=np.bool_)
    ixy = np.empty(m)
    izx = np.empty(m)
    iyz = np.empty(m)
    for x in range(mx):
        for y in range(my):
            for z in range(mz):
                if not known[x, y, z]:
                    continue
                ip = _nh_mean(img, x, y, z, nr)
                for i in range(m):
                    a, b, c = mask[i, 0], mask[i, 1], mask[i, 2]
                    ixy[i] = _nh_mean(img, x + a, y + b, z + c, nr)
                    izx[i] = _nh_mean(img, x + c, y + a, z + b, nr)
                    iyz[i] = _nh_mean(img, x + b, y + c, z + a, nr)
                hit = (rfast(ip, ixy, s, th, n, 1.0) or rfast(ip, izx, s, th, n, 1.0)
                       or rfast(ip, iyz, s, th, n, 1.0))
                if not hit and both:
                    hit = (rfast(ip, ixy, s, th, n, -1.0) or rfast(ip, izx, s, th, n, -1.0)
                           or rfast(ip, iyz, s, th, n, -1.0))
                out[x, y, z] = hit
    return out


def contrast_candidates(img: np.ndarray, known: np.ndarray, reach: int, th: float) -> np.ndarray:
    """Known cells whose cube of half-size reach (outside reads 0) spans more than th in intensity: no
    other cell can pass rFAST, whose ring and centre means all lie inside that cube. Skips the flat
    free space that is most of a map before the ring is read."""
    size = 2 * reach + 1
    spread = ndimage.maximum_filter(img, size=size, mode="constant") - ndimage.minimum_filter(
        img, size=size, mode="constant")
    return known & (spread > th)


def fast3d(img: np.ndarray, known: np.ndarray, params: MergeParams) -> np.ndarray:
    """Keypoint cells (k, 3) int64 array indices of the preprocessed image."""
    mask = circle_mask(params.fast_radius)
    th = float(params.fast_threshold)
    nr = params.descriptor_neighbourhood
    candidates = contrast_candidates(img, known, int(np.abs(mask).max()) + nr, th)
    hits = fast3d_mask(img, candidates, mask, params.fast_continuity, th, nr, params.fast_both_polarities)
    return np.argwhere(hits).astype(np.int64)

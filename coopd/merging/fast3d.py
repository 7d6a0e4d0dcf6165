"""FAST 3D keypoint detection (§8.2, Algorithms 2 and 3): rFAST on the XY, ZX and YZ planes."""

import numba as nb
import numpy as np

from coopd.kernel_cache import CACHE as KERNEL_CACHE

from .params import MergeParams

_JIT = {"nogil": True, "cache": KERNEL_CACHE}


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
def _rings_pass(flat, c, cube, rings, ring, s, th, n, both):
    """rFAST on the three planes' rings around flat index c of the zero-padded image: each sample is
    the mean of the cube offsets around it (getCellNhMean), the centre too."""
    m = rings.shape[1]
    ip = 0.0
    for q in range(cube.shape[0]):
        ip += flat[c + cube[q]]
    ip /= cube.shape[0]
    for plane in range(3):
        for i in range(m):
            acc = 0.0
            for q in range(cube.shape[0]):
                acc += flat[c + rings[plane, i] + cube[q]]
            ring[i] = acc / cube.shape[0]
        if rfast(ip, ring, s, th, n, 1.0) or (both and rfast(ip, ring, s, th, n, -1.0)):
            return True
    return False


@nb.njit(**_JIT)
def _fast3d_cells(flat, cells, cube, rings, n, th, both):
    """Algorithm 2 over the given flat indices of the padded image: True where a cell passes rFAST on
    any of the three planes."""
    m = rings.shape[1]
    s = m // 4
    ring = np.empty(m)
    out = np.zeros(cells.shape[0], dtype=np.bool_)
    for i in range(cells.shape[0]):
        out[i] = _rings_pass(flat, cells[i], cube, rings, ring, s, th, n, both)
    return out


def fast3d_mask(img: np.ndarray, known: np.ndarray, mask: np.ndarray, n: int, th: float, nr: int,
                both: bool) -> np.ndarray:
    """Algorithm 2: True where a known cell passes rFAST on the XY, ZX or YZ plane. The image is padded
    with zeros (outside reads 0) so that every ring and neighbourhood sample is one flat offset."""
    pad = int(np.abs(mask).max()) + nr
    padded = np.pad(np.asarray(img, dtype=np.float64), pad)
    strides = np.array(padded.strides) // padded.itemsize
    r = np.arange(-nr, nr + 1)
    cube = (np.stack(np.meshgrid(r, r, r, indexing="ij"), -1).reshape(-1, 3) @ strides).astype(np.int64)
    a, b, c = mask[:, 0], mask[:, 1], mask[:, 2]
    planes = [np.stack(p, 1) for p in ((a, b, c), (c, a, b), (b, c, a))]  # XY, ZX, YZ as in the thesis
    rings = np.stack([p @ strides for p in planes]).astype(np.int64)
    idx = np.argwhere(known)
    cells = ((idx + pad) @ strides).astype(np.int64)
    out = np.zeros(img.shape, dtype=np.bool_)
    if len(idx):
        hits = _fast3d_cells(padded.reshape(-1), cells, cube, rings, n, float(th), bool(both))
        out[tuple(idx[hits].T)] = True
    return out


WINDOW_CHUNK = 256
"""Columns filtered together by _window_max_middle: its buffers stay in the CPU cache."""


@nb.njit(**_JIT)
def _window_max_middle(src, radius, dst):
    """dst[p, i, m] = max of src[p, i - radius .. i + radius, m], reading 0 outside; src, dst C-contiguous
    (P, n, M). van Herk / Gil-Werman (block prefix and suffix maxima: three passes whatever the radius),
    on up to WINDOW_CHUNK columns at once so that the inner loops read contiguous memory."""
    big_p, n, big_m = src.shape
    w = 2 * radius + 1
    size = n + 2 * radius
    chunk = min(WINDOW_CHUNK, big_m)
    padded = np.zeros((size, chunk), src.dtype)  # rows < radius and >= radius + n stay 0: the outside
    g = np.empty((size, chunk), src.dtype)
    h = np.empty((size, chunk), src.dtype)
    for p in range(big_p):
        for m0 in range(0, big_m, chunk):
            cols = min(chunk, big_m - m0)
            for k in range(n):
                for c in range(cols):
                    padded[radius + k, c] = src[p, k, m0 + c]
            for i in range(size):
                if i % w == 0:
                    for c in range(cols):
                        g[i, c] = padded[i, c]
                else:
                    for c in range(cols):
                        g[i, c] = max(g[i - 1, c], padded[i, c])
            for i in range(size - 1, -1, -1):
                if i == size - 1 or (i + 1) % w == 0:
                    for c in range(cols):
                        h[i, c] = padded[i, c]
                else:
                    for c in range(cols):
                        h[i, c] = max(h[i + 1, c], padded[i, c])
            for i in range(n):  # the window rows i .. i + w - 1 of the padded line: a block's tail and head
                for c in range(cols):
                    dst[p, i, m0 + c] = max(h[i, c], g[i + w - 1, c])


def window_max(img: np.ndarray, reach: int) -> np.ndarray:
    """Max of img over the cube of half-size reach around each cell, reading 0 outside the image
    (scipy.ndimage.maximum_filter with mode "constant", without scipy), one axis at a time; the last
    axis through a transposed copy, so that every pass runs over many contiguous columns."""
    src = np.ascontiguousarray(img)
    for axis in (0, 1):
        shape = src.shape
        middle = (int(np.prod(shape[:axis])), shape[axis], int(np.prod(shape[axis + 1:])))
        dst = np.empty_like(src)
        _window_max_middle(src.reshape(middle), reach, dst.reshape(middle))
        src = dst
    last = np.ascontiguousarray(src.reshape(-1, src.shape[2]).T)  # (n, M): the last axis in the middle
    dst = np.empty_like(last)
    _window_max_middle(last[None], reach, dst[None])
    return np.ascontiguousarray(dst.T).reshape(src.shape)


def contrast_candidates(img: np.ndarray, known: np.ndarray, reach: int, th: float) -> np.ndarray:
    """Known cells whose cube of half-size reach (outside reads 0) spans more than th in intensity: no
    other cell can pass rFAST, whose ring and centre means all lie inside that cube. Skips the flat
    free space that is most of a map before the ring is read."""
    spread = window_max(img, reach) + window_max(-img, reach)  # max - min: min(x) = -max(-x), 0 = -0
    return known & (spread > th)


def fast3d(img: np.ndarray, known: np.ndarray, params: MergeParams) -> np.ndarray:
    """Keypoint cells (k, 3) int64 array indices of the preprocessed image."""
    mask = circle_mask(params.fast_radius)
    th = float(params.fast_threshold)
    nr = params.descriptor_neighbourhood
    candidates = contrast_candidates(img, known, int(np.abs(mask).max()) + nr, th)
    hits = fast3d_mask(img, candidates, mask, params.fast_continuity, th, nr, params.fast_both_polarities)
    return np.argwhere(hits).astype(np.int64)

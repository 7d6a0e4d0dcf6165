"""Gravity-aligned global search: every yaw, every horizontal shift, scored by FFT correlation of
top-view wall images with a free-space penalty; the vertical offset from floor/ceiling histograms.

Drones share gravity through their IMUs, so two maps differ by yaw + translation (roll and pitch of a
few degrees are left to the refinement). Walls are vertical: seen from above they are the columns
with several occupied cells. A shift that lays one map's walls onto the other's walls scores, one
that lays them onto space the other map saw free is penalised, which is what separates the true
alignment from 90/180-degree flips and shifts along repeated walls.
"""

from dataclasses import dataclass

import numba as nb
import numpy as np

from coopd.kernel_cache import CACHE as KERNEL_CACHE

from ..geometry import rigid, rotation_z
from ..grid import OccupancyGrid
from .params import MergeParams

_JIT = {"nogil": True, "cache": KERNEL_CACHE}


@dataclass(frozen=True)
class TopView:
    """Columns of a map's slab between floor and ceiling: occupied counts (walls weigh by height) and
    columns seen entirely free."""

    walls: np.ndarray
    wall_weight: np.ndarray
    free: np.ndarray


def height_histogram(grid: OccupancyGrid, threshold: int) -> tuple[np.ndarray, float]:
    """Occupied cells per z layer and the height (metres) of layer 0."""
    occ = grid.cells >= threshold
    return occ.sum(axis=(0, 1)).astype(np.float64), float(grid.offset[2] * grid.resolution)


def floor_and_ceiling(hist: np.ndarray, z0: float, resolution: float) -> tuple[float, float]:
    """Heights of the strongest occupied layer in the lower and in the upper part of the occupied range."""
    nz = np.flatnonzero(hist)
    if len(nz) == 0:
        return z0, z0
    lo, hi = nz[0], nz[-1]
    cut = lo + (hi - lo) // 2
    f = lo + int(np.argmax(hist[lo:cut + 1]))
    c = cut + int(np.argmax(hist[cut:hi + 1]))
    return z0 + f * resolution, z0 + c * resolution


def top_view(grid: OccupancyGrid, z_lo: float, z_hi: float, params: MergeParams) -> TopView:
    """Top view of the slab z_lo..z_hi (metres, map frame): wall columns and all-free columns."""
    res = grid.resolution
    k0 = int(np.floor(z_lo / res + 0.5)) - grid.offset[2]
    k1 = int(np.floor(z_hi / res + 0.5)) - grid.offset[2]
    k0, k1 = max(k0, 0), min(k1, grid.shape[2] - 1)
    if k1 < k0:
        return TopView(np.empty((0, 2)), np.empty(0), np.empty((0, 2)))
    slab = grid.cells[:, :, k0:k1 + 1]
    occ = (slab >= params.occupied_threshold).sum(axis=2)
    free = ((slab >= 0) & (slab < params.occupied_threshold)).sum(axis=2)
    ij = np.argwhere(occ >= params.search_wall_cells)
    fj = np.argwhere((occ == 0) & (free >= params.search_free_cells))
    off = grid.offset[:2]
    weight = np.minimum(occ[ij[:, 0], ij[:, 1]], params.search_wall_weight_cap).astype(np.float32)
    return TopView((ij + off) * res, weight, (fj + off) * res)


@nb.njit(**_JIT)
def _raster_into(img, points, weights, c, s, origin, cell):
    """img[pixel] = max weight of the points, turned by the yaw (cos c, sin s), falling in it."""
    nx, ny = img.shape
    for i in range(points.shape[0]):
        x = c * points[i, 0] - s * points[i, 1]
        y = s * points[i, 0] + c * points[i, 1]
        ix = int(np.floor((x - origin[0]) / cell))
        iy = int(np.floor((y - origin[1]) / cell))
        if 0 <= ix < nx and 0 <= iy < ny and weights[i] > img[ix, iy]:
            img[ix, iy] = weights[i]


@nb.njit(**_JIT)
def _clear_near_walls(free, walls):
    """Drop free pixels within one pixel of a wall pixel (a wall's own pixel holds the free columns
    in front of it, which must not count against a wall laid there)."""
    nx, ny = free.shape
    for x in range(nx):
        for y in range(ny):
            if walls[x, y] > 0:  # walls are few: clear around each, rather than search around each free pixel
                for a in range(max(0, x - 1), min(nx, x + 2)):
                    for b in range(max(0, y - 1), min(ny, y + 2)):
                        free[a, b] = 0


def _images(view: TopView, yaw: float, origin: np.ndarray, cell: float, n: tuple):
    """(wall image, free image) of a top view turned by yaw, pixel [0, 0] at origin."""
    c, s = float(np.cos(yaw)), float(np.sin(yaw))
    walls = np.zeros(n, dtype=np.float32)
    free = np.zeros(n, dtype=np.float32)
    _raster_into(walls, view.walls, view.wall_weight, c, s, origin, cell)
    _raster_into(free, view.free, np.ones(len(view.free), dtype=np.float32), c, s, origin, cell)
    _clear_near_walls(free, walls)
    return walls, free


@nb.njit(**_JIT)
def _peaks(score, count, rad):
    """(scores, rows, columns) of the count best cells of score, each found after the square of
    half-size rad around the ones before was suppressed (wrapping: the shifts are cyclic); ties go
    to the first cell in array order. score is overwritten."""
    n0, n1 = score.shape
    scores = np.empty(count)
    rows = np.empty(count, dtype=np.int64)
    cols = np.empty(count, dtype=np.int64)
    for k in range(count):
        flat = np.argmax(score)
        i, j = flat // n1, flat % n1
        scores[k], rows[k], cols[k] = score[i, j], i, j
        for a in range(i - rad, i + rad + 1):
            for b in range(j - rad, j + rad + 1):
                score[a % n0, b % n1] = -np.inf
    return scores, rows, cols


def vertical_offset(ha: np.ndarray, za: float, hb: np.ndarray, zb: float, resolution: float) -> float:
    """tz (metres) aligning b's occupied-height histogram to a's (floors and ceilings line up)."""
    if ha.sum() == 0 or hb.sum() == 0:
        return 0.0
    c = np.correlate(ha, hb, mode="full")
    lag = int(np.argmax(c)) - (len(hb) - 1)
    return za - zb + lag * resolution


def fast_fft_length(n: int) -> int:
    """The smallest 5-smooth length (2^a 3^b 5^c) >= n: the sizes FFTs are fastest at."""
    best = 1 << max(0, (n - 1).bit_length())  # a power of two always qualifies
    p5 = 1
    while p5 < best:
        p35 = p5
        while p35 < best:
            p = p35 << max(0, (-(-n // p35) - 1).bit_length())  # times the power of two reaching n
            best = min(best, p)
            p35 *= 3
        p5 *= 5
    return best


def search(a_grid: OccupancyGrid, b_grid: OccupancyGrid, params: MergeParams,
           limit: int | None = None) -> list[tuple[float, np.ndarray]]:
    """(correlation score, 4x4 b -> a) for the best peaks over all yaws (the first `limit` of them),
    strongest first."""
    res = a_grid.resolution
    ha, za = height_histogram(a_grid, params.occupied_threshold)
    hb, zb = height_histogram(b_grid, params.occupied_threshold)
    tz = vertical_offset(ha, za, hb, zb, res)
    floor, ceiling = floor_and_ceiling(ha, za, res)
    margin = min(params.search_slab_margin_m, (ceiling - floor) / 4)
    z_lo, z_hi = floor + margin, ceiling - margin
    if z_hi <= z_lo:
        z_lo, z_hi = floor, ceiling
    a = top_view(a_grid, z_lo, z_hi, params)
    b = top_view(b_grid, z_lo - tz, z_hi - tz, params)
    if len(a.walls) == 0 or len(b.walls) == 0:
        return []
    cell = params.search_cell_m
    a_pts = np.concatenate([a.walls, a.free])
    a_org = a_pts.min(axis=0)
    a_ext = np.ceil((a_pts.max(axis=0) - a_org) / cell).astype(int) + 1
    centre = b.walls.mean(axis=0)
    b = TopView(b.walls - centre, b.wall_weight, b.free - centre)
    b_rad = float(np.max(np.linalg.norm(np.concatenate([b.walls, b.free]), axis=1)))
    b_ext = int(np.ceil(2 * b_rad / cell)) + 2
    n = tuple(fast_fft_length(int(e + b_ext)) for e in a_ext)
    wa_img, fa_img = _images(a, 0.0, a_org, cell, n)
    wa, fa = np.fft.rfft2(wa_img), np.fft.rfft2(fa_img)
    lam = params.search_free_penalty
    b_org = np.array([-b_rad, -b_rad])
    rad = int(np.ceil(params.search_suppress_m / cell))
    peaks = []
    for yaw in np.radians(np.arange(0.0, 360.0, params.search_yaw_step_deg)):
        wb_img, fb_img = _images(b, yaw, b_org, cell, n)
        wb, fb = np.conj(np.fft.rfft2(wb_img)), np.conj(np.fft.rfft2(fb_img))
        score = np.fft.irfft2(wa * wb - lam * (wa * fb + fa * wb), s=n)
        scores, rows, cols = _peaks(score, params.search_peaks_per_yaw, rad)
        peaks += [(float(s), yaw, int(i), int(j)) for s, i, j in zip(scores, rows, cols, strict=True)]
    peaks.sort(key=lambda x: -x[0])
    scores = np.array([p[0] for p in peaks])
    yaws = np.array([p[1] for p in peaks])
    rows = np.array([p[2] for p in peaks])
    cols = np.array([p[3] for p in peaks])
    si = np.where(rows <= a_ext[0], rows, rows - n[0])  # shifts span [-b_ext, a_ext]: one period
    sj = np.where(cols <= a_ext[1], cols, cols - n[1])
    landing = a_org - b_org + np.stack([si, sj], axis=1) * cell  # where b's wall centre lands in a
    if params.search_distinct_deg > 0:
        keep = distinct_peaks(yaws, landing, np.radians(params.search_distinct_deg),
                              params.search_distinct_m, limit)
    else:
        keep = list(range(len(peaks)))[:limit]
    found = []
    for k in keep:
        t_xy = landing[k] - rotation_z(yaws[k])[:2, :2] @ centre
        found.append((float(scores[k]), rigid(rotation_z(yaws[k]), [t_xy[0], t_xy[1], tz])))
    return found


def distinct_peaks(yaws: np.ndarray, landing: np.ndarray, min_yaw: float, min_shift: float,
                   limit: int | None = None) -> list[int]:
    """Indices of the peaks (strongest first) kept by non-maximum suppression across yaws: a peak
    within min_yaw (radians) and min_shift (metres, where b's centre lands) of a stronger kept one
    is a near-copy of it (neighbouring yaw steps of one rotation) and is dropped, so the hypotheses
    refined are different rotations or places rather than one rotation several times."""
    keep: list[int] = []
    for k in range(len(yaws)):
        if limit is not None and len(keep) >= limit:
            break
        if keep:
            turn = np.abs(np.angle(np.exp(1j * (yaws[keep] - yaws[k]))))
            apart = np.linalg.norm(landing[keep] - landing[k], axis=1)
            if np.any((turn <= min_yaw) & (apart <= min_shift)):
                continue
        keep.append(k)
    return keep

"""Brute-force numpy reference of coopd.grid.sectors.sector_distances: every column of the whole map's
band (and every column off the map within range, unknown) -> class, distance, sectors -> min per
sector. Slow and obvious; the tests and scripts/bench obstacles check the kernel against it."""

import numpy as np

from coopd.grid.sectors import CM_EPS, NO_DATA, SECTOR_DEG, SECTORS


def reference_sectors(grid, z_keys, position, yaw, min_distance, max_distance, threshold) -> np.ndarray:
    res = grid.resolution
    px, py = float(position[0]), float(position[1])
    g_lo, g_hi = grid.key_bounds()
    z0, z1 = z_keys
    band = grid.cells[:, :, max(z0, g_lo[2]) - g_lo[2]:min(z1, g_hi[2]) - g_lo[2] + 1]
    partial = z0 < g_lo[2] or z1 > g_hi[2]
    occupied = (band >= threshold).any(axis=2).ravel()
    unknown = (band < 0).any(axis=2).ravel() | partial
    kx, ky = np.meshgrid(np.arange(g_lo[0], g_hi[0] + 1), np.arange(g_lo[1], g_hi[1] + 1), indexing="ij")
    kx, ky = kx.ravel(), ky.ravel()
    # columns off the map but within reach: unknown
    reach = int(np.ceil(max_distance / res)) + 2
    ox, oy = np.meshgrid(np.arange(int(np.floor(px / res)) - reach, int(np.ceil(px / res)) + reach + 1),
                         np.arange(int(np.floor(py / res)) - reach, int(np.ceil(py / res)) + reach + 1),
                         indexing="ij")
    ox, oy = ox.ravel(), oy.ravel()
    off = (ox < g_lo[0]) | (ox > g_hi[0]) | (oy < g_lo[1]) | (oy > g_hi[1])
    kx = np.concatenate([kx, ox[off]])
    ky = np.concatenate([ky, oy[off]])
    occupied = np.concatenate([occupied, np.zeros(int(off.sum()), bool)])
    unknown = np.concatenate([unknown, np.ones(int(off.sum()), bool)])

    cx, cy = kx * res, ky * res
    half = 0.5 * res
    ex = np.maximum(np.abs(cx - px) - half, 0.0)
    ey = np.maximum(np.abs(cy - py) - half, 0.0)
    d = np.sqrt(ex * ex + ey * ey)
    keep = (d >= min_distance) & (d <= max_distance) & (occupied | unknown)
    cx, cy, d, occupied = cx[keep], cy[keep], d[keep], occupied[keep]
    centre = np.arctan2(cy - py, cx - px)
    lo = np.zeros_like(d)
    hi = np.zeros_like(d)
    for sx in (-half, half):
        for sy in (-half, half):
            a = np.arctan2(cy + sy - py, cx + sx - px) - centre
            a = np.where(a > np.pi, a - 2 * np.pi, np.where(a < -np.pi, a + 2 * np.pi, a))
            lo, hi = np.minimum(lo, a), np.maximum(hi, a)
    deg = 180.0 / np.pi
    first = np.floor(((yaw - centre - hi) * deg + 0.5 * SECTOR_DEG) / SECTOR_DEG).astype(np.int64)
    last = np.floor(((yaw - centre - lo) * deg + 0.5 * SECTOR_DEG) / SECTOR_DEG).astype(np.int64)
    occupied_d = np.full(SECTORS, np.inf)
    unknown_d = np.full(SECTORS, np.inf)
    for j in range(int((last - first).max(initial=-1)) + 1):
        m = first + j <= last
        np.minimum.at(occupied_d, (first + j)[m & occupied] % SECTORS, d[m & occupied])
        np.minimum.at(unknown_d, (first + j)[m & ~occupied] % SECTORS, d[m & ~occupied])
    max_cm = int(np.floor(max_distance * 100.0))
    out = np.full(SECTORS, max_cm + 1, dtype=np.uint16)
    out[unknown_d <= max_distance] = NO_DATA
    hit = (occupied_d <= unknown_d) & (occupied_d <= max_distance)
    out[hit] = np.minimum(np.floor(occupied_d[hit] * 100.0 + CM_EPS).astype(np.int64), max_cm)
    return out

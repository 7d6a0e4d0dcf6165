"""Obstacle distance per horizontal sector around the vehicle, read from the occupancy grid: what
MAVLink OBSTACLE_DISTANCE carries (72 sectors of 5 degrees, index 0 forward, clockwise as body FRD,
centimetres), for PX4 collision prevention and ArduPilot proximity.

Only a window around the vehicle is read (read_window, under the grid owner's lock): the horizontal
box within max range, the layers of the band the vehicle flies in. Each column of the window (one
x, y cell, the band's layers) is
  occupied: some cell in the band is occupied (>= threshold);
  free:     every cell in the band is known free (0 <= p < threshold);
  unknown:  otherwise (an unknown or inaccessible cell in the band, nothing occupied).
A column covers the sectors its square footprint spans as seen from the vehicle, at the distance of
its nearest point. Columns nearer than min range (the vehicle itself) or beyond max range are left
out. A sector then reports
  the distance of its nearest occupied column, when no unknown column is nearer (an obstacle);
  NO_DATA (UINT16_MAX) when an unknown column comes first (the map does not know: never "free");
  max range + 1 cm when every column in it up to max range is known free.
"""

import functools
import math

import numba as nb
import numpy as np

from coopd.kernel_cache import CACHE as KERNEL_CACHE

from .cells import CELL_DTYPE, UNKNOWN

SECTORS = 72
SECTOR_DEG = 5.0
NO_DATA = 65535
"""UINT16_MAX: no data for the sector."""
CM_EPS = 1e-6
"""Distances are floored to whole centimetres; this much (1e-8 m) absorbs binary rounding, so a
face at 1.95 m reads 195 cm, not 194."""

_JIT = {"nogil": True, "cache": KERNEL_CACHE, "boundscheck": False}


def band_keys(z_m: float, below_m: float, above_m: float, resolution: float) -> tuple[int, int]:
    """Inclusive z key range of the cells whose centres lie in [z - below, z + above]; at least the
    cell holding z when the band is thinner than a cell."""
    lo = math.ceil((z_m - below_m) / resolution - 1e-9)
    hi = math.floor((z_m + above_m) / resolution + 1e-9)
    if hi < lo:
        lo = hi = math.floor(z_m / resolution + 0.5)
    return lo, hi


def window_keys(x_m: float, y_m: float, z_keys: tuple[int, int], max_distance_m: float,
                resolution: float) -> tuple[np.ndarray, np.ndarray]:
    """Inclusive key box (lo, hi) of every column whose nearest point can be within max range of
    (x, y), over the band's layers."""
    reach = max_distance_m / resolution + 1.0
    lo = np.array([math.floor(x_m / resolution - reach), math.floor(y_m / resolution - reach), z_keys[0]])
    hi = np.array([math.ceil(x_m / resolution + reach), math.ceil(y_m / resolution + reach), z_keys[1]])
    return lo.astype(np.int64), hi.astype(np.int64)


def window_cells(lo_key, hi_key) -> int:
    """Cells of the inclusive key box (what read_window copies)."""
    return int(np.prod(np.asarray(hi_key, dtype=np.int64) - np.asarray(lo_key, dtype=np.int64) + 1))


def read_window(grid, lo_key, hi_key, out: np.ndarray | None = None) -> np.ndarray:
    """The grid's cells in the inclusive key box, UNKNOWN where the grid does not reach; copies only
    the overlap (the caller holds the grid owner's lock while this runs). `out` is reused if given."""
    lo_key = np.asarray(lo_key, dtype=np.int64)
    hi_key = np.asarray(hi_key, dtype=np.int64)
    shape = tuple(int(s) for s in hi_key - lo_key + 1)
    if out is None or out.shape != shape:
        out = np.empty(shape, dtype=CELL_DTYPE)
    out.fill(UNKNOWN)
    g_lo, g_hi = grid.key_bounds()
    a, b = np.maximum(lo_key, g_lo), np.minimum(hi_key, g_hi)
    if np.all(b >= a):
        out[a[0] - lo_key[0]:b[0] - lo_key[0] + 1, a[1] - lo_key[1]:b[1] - lo_key[1] + 1,
            a[2] - lo_key[2]:b[2] - lo_key[2] + 1] = grid.block(a, b)
    return out


def overlay(fresh: np.ndarray, older: np.ndarray) -> np.ndarray:
    """fresh where it knows the cell, older where fresh is unknown (in place in fresh)."""
    np.copyto(fresh, older, where=fresh == UNKNOWN)
    return fresh


@functools.lru_cache(maxsize=8)
def ring_order(radius_cells: int) -> tuple[np.ndarray, np.ndarray]:
    """Column offsets (dx, dy) from the vehicle's cell within radius_cells, nearest first, and a lower
    bound (in cells) of the nearest-point distance of each from a vehicle anywhere in its cell."""
    r = np.arange(-radius_cells, radius_cells + 1)
    dx, dy = (a.ravel() for a in np.meshgrid(r, r, indexing="ij"))
    centre = np.sqrt(dx * dx + dy * dy)
    keep = centre <= radius_cells
    order = np.argsort(centre[keep], kind="stable")
    offsets = np.stack([dx[keep], dy[keep]], axis=1)[order].astype(np.int64)
    return offsets, np.maximum(centre[keep][order] - math.sqrt(2.0), 0.0)


@nb.njit(**_JIT)
def sector_distances(cells, key_x0, key_y0, resolution, px, py, yaw, min_distance, max_distance,
                     threshold, offsets, bounds):
    """OBSTACLE_DISTANCE distances (uint16 cm, 72 sectors, 0 forward, clockwise) of a band window.

    cells: (nx, ny, nz) int8, the band's layers of the columns keyed key_x0.., key_y0..; (px, py)
    the vehicle in the map frame (ENU, metres), yaw its heading (body x from east, counter-clockwise,
    radians); distances in metres; offsets, bounds: ring_order() of at least max range + 3 cells.
    Columns are visited nearest first and the visit ends once no farther column can be nearer than
    what every sector already holds (the result is that of visiting all). See the module docstring."""
    nx, ny, nz = cells.shape
    occupied_d = np.full(SECTORS, np.inf)
    unknown_d = np.full(SECTORS, np.inf)
    half = 0.5 * resolution
    deg = 180.0 / np.pi
    vx = int(np.floor(px / resolution + 0.5)) - key_x0
    vy = int(np.floor(py / resolution + 0.5)) - key_y0
    settled = np.inf  # the farthest first hit over the sectors, once every sector has one
    for n in range(offsets.shape[0]):
        reach = bounds[n] * resolution
        if reach > max_distance or reach > settled:
            break
        ix = vx + offsets[n, 0]
        iy = vy + offsets[n, 1]
        if ix < 0 or iy < 0 or ix >= nx or iy >= ny:
            continue
        cx = (key_x0 + ix) * resolution
        cy = (key_y0 + iy) * resolution
        ex = max(abs(cx - px) - half, 0.0)
        ey = max(abs(cy - py) - half, 0.0)
        d = np.sqrt(ex * ex + ey * ey)
        if d < min_distance or d > max_distance:
            continue
        occupied = False
        unknown = False
        column = cells[ix, iy]
        for iz in range(nz):
            v = column[iz]
            if v >= threshold:
                occupied = True
                break
            if v < 0:
                unknown = True
        if not (occupied or unknown):
            continue
        centre = np.arctan2(cy - py, cx - px)
        lo = 0.0
        hi = 0.0
        for corner in range(4):
            qx = cx + (half if corner & 1 else -half)
            qy = cy + (half if corner & 2 else -half)
            a = np.arctan2(qy - py, qx - px) - centre
            if a > np.pi:
                a -= 2.0 * np.pi
            elif a < -np.pi:
                a += 2.0 * np.pi
            lo = min(lo, a)
            hi = max(hi, a)
        # clockwise bearing from forward: -(angle - yaw); the counter-clockwise extent flips
        first = int(np.floor(((yaw - centre - hi) * deg + 0.5 * SECTOR_DEG) / SECTOR_DEG))
        last = int(np.floor(((yaw - centre - lo) * deg + 0.5 * SECTOR_DEG) / SECTOR_DEG))
        for s in range(first, last + 1):
            k = s % SECTORS
            if occupied:
                if d < occupied_d[k]:
                    occupied_d[k] = d
            elif d < unknown_d[k]:
                unknown_d[k] = d
        settled = 0.0
        for k in range(SECTORS):
            settled = max(settled, min(occupied_d[k], unknown_d[k]))
    out = np.empty(SECTORS, dtype=np.uint16)
    max_cm = int(np.floor(max_distance * 100.0))
    for k in range(SECTORS):
        if occupied_d[k] <= unknown_d[k] and occupied_d[k] <= max_distance:
            out[k] = min(int(np.floor(occupied_d[k] * 100.0 + CM_EPS)), max_cm)
        elif unknown_d[k] <= max_distance:
            out[k] = NO_DATA
        else:
            out[k] = max_cm + 1
    return out


def sector_distances_of(cells: np.ndarray, lo_key, resolution: float, position, yaw: float,
                        min_distance_m: float, max_distance_m: float, threshold: int) -> np.ndarray:
    """sector_distances on a window read at key lo_key, for a vehicle at `position` (map frame)."""
    offsets, bounds = ring_order(int(math.ceil(max_distance_m / resolution)) + 3)
    return sector_distances(cells, int(lo_key[0]), int(lo_key[1]), float(resolution), float(position[0]),
                            float(position[1]), float(yaw), float(min_distance_m), float(max_distance_m),
                            int(threshold), offsets, bounds)

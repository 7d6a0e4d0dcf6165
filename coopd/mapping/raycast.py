"""numba kernels that turn one depth frame into cell updates (thesis Algorithm 1, notes §3).

Every valid pixel is a ray from the sensor origin to its measured point, walked cell by cell by
one of two traversals. A ray longer than max range is cut there and ends in a miss, not a hit
(OctoMap's maxrange); a pixel whose depth reads beyond max range (up to `far_limit`) is such a
ray, so far readings clear the free space in front of them. Depth 0, NaN, negative or beyond
`far_limit` is no reading at all and touches nothing.

- Bresenham (default): the thesis' 3D Bresenham line between the centres of the origin cell and
  the end cell; one cell per step of the major axis (26-connected).
- exact (Amanatides–Woo): every cell the segment crosses (6-connected), a superset of the cells
  Bresenham picks for the same segment, at about twice the cell visits.

Two ways to apply HIMM along the rays:

- mark mode (default): rays only *mark* cells of a per-frame scratch box (hit wins over miss),
  then each marked cell gets one HIMM update. Rays can be split among threads, each with its own
  scratch, and the result is identical to one thread's.
- per-ray mode (the thesis' literal reading): each ray updates the grid as it walks. One thread.

In both, a miss spares an occupied cell of a floor, ceiling or table top that the ray only grazes
(_grazes, MapperConfig.graze_deg): the ray crosses the free part of a cell that holds the surface.
"""

import numba as nb
import numpy as np

from coopd.kernel_cache import CACHE as KERNEL_CACHE

from ..grid.cells import INACCESSIBLE, OCCUPIED_THRESHOLD, P_MAX, P_MIN, P_PRIOR, UNKNOWN
from ..grid.kernels import free_side

_JIT = {"nogil": True, "cache": KERNEL_CACHE, "boundscheck": False, "error_model": "numpy"}

MODE_MARK = 0
MODE_PER_RAY = 1

TRAVERSAL_BRESENHAM = 0
TRAVERSAL_EXACT = 1

MARK_MISS = 1
"""Mark bits of the per-frame scratch: some ray passed through the cell ..."""
MARK_HIT = 2
"""... some ray ended in it (a hit wins over misses when applied) ..."""
MARK_WALKED = 4
"""... and a Bresenham walk already ended in it, so later rays ending there share its path."""

LEVEL_MIN = 0.7
"""A ray spares only the cells of level surfaces (floors, ceilings, table tops: free side within 45
degrees of vertical) that it grazes. Drones fly parallel to those and see them edge-on all the time;
a wall seen edge-on down a corridor is cleared as before, so a wall that odometry drift mapped twice,
a few centimetres apart, does not stay twice (docs/mapping.md, "Rays that graze a surface")."""

COUNT_RAYS = 0
COUNT_INVALID = 1
COUNT_TRUNCATED = 2
COUNT_VISITS = 3
N_COUNTS = 4


@nb.njit(**_JIT)
def endpoint_bounds(depth, scale, slope_x, slope_y, rot, origin, min_range, max_range, far_limit):
    """Map-frame box (lo, hi, metres) holding the origin and every valid ray's end point (cut at
    max range), and the number of valid rays (depth in min_range..far_limit)."""
    lo = origin.copy()
    hi = origin.copy()
    valid = 0
    h, w = depth.shape
    for v in range(h):
        sy = slope_y[v]
        for u in range(w):
            z = depth[v, u] * scale
            if not (z >= min_range and z <= far_limit):
                continue
            valid += 1
            x = slope_x[u] * z
            y = sy * z
            length = np.sqrt(x * x + y * y + z * z)
            f = 1.0
            if length > max_range:
                f = max_range / length
            for a in range(3):
                p = origin[a] + (rot[a, 0] * x + rot[a, 1] * y + rot[a, 2] * z) * f
                if p < lo[a]:
                    lo[a] = p
                if p > hi[a]:
                    hi[a] = p
    return lo, hi, valid


@nb.njit(inline="always")
def _visit(target, idx, is_hit, mode, inc, dec):
    if mode == MODE_MARK:
        target[idx] |= MARK_HIT if is_hit else MARK_MISS
    else:
        c = target[idx]
        if c == INACCESSIBLE:
            return
        if c == UNKNOWN:
            c = P_PRIOR
        if is_hit:
            c = min(c + inc, P_MAX)
        else:
            c = max(c - dec, P_MIN)
        target[idx] = c


@nb.njit(inline="always")
def _grazes(cells, box_lo, ix, iy, iz, ux, uy, uz, graze_sin):
    """Whether a ray along the unit (ux, uy, uz) only grazes the surface in the grid cell of box cell
    (ix, iy, iz): the cell is occupied and the ray runs within asin(graze_sin) of its surface (the
    plane across its free-side normal). Such a ray passes through the free part of a cell that holds
    a surface (a floor seen edge-on from a drone on the ground) and is no evidence that the cell is
    empty. Only level surfaces are spared (LEVEL_MIN); a cell with no free-side normal (free all
    round, as noise in free space) is not."""
    if graze_sin <= 0.0:
        return False
    gx, gy, gz = ix + box_lo[0], iy + box_lo[1], iz + box_lo[2]
    mx, my, mz = cells.shape
    if gx < 0 or gy < 0 or gz < 0 or gx >= mx or gy >= my or gz >= mz:
        return False
    if cells[gx, gy, gz] < OCCUPIED_THRESHOLD:
        return False
    n = free_side(cells, OCCUPIED_THRESHOLD, gx, gy, gz)
    if abs(n[2]) < LEVEL_MIN:
        return False
    return abs(n[0] * ux + n[1] * uy + n[2] * uz) < graze_sin


@nb.njit(inline="always")
def _axis_setup(a, b):
    """Step, cells to go, next boundary crossing (ray parameter t) and t per cell along one axis."""
    i = np.floor(a)
    e = np.floor(b)
    d = b - a
    if d > 0:
        return 1, int(e - i), (i + 1.0 - a) / d, 1.0 / d
    if d < 0:
        return -1, int(i - e), (i - a) / d, -1.0 / d
    return 0, 0, np.inf, np.inf


@nb.njit(inline="always")
def _walk(target, shape, ax, ay, az, bx, by, bz, hit, hit_from_t, mode, inc, dec, cells, box_lo, graze_sin):
    """Visit every cell the segment a→b crosses; cells entered after hit_from_t (and the end
    cell) are hits when `hit`, all others misses, except the occupied cells the segment only grazes
    (_grazes), which it leaves alone. Coordinates are continuous cell units."""
    sxs, rx, tmx, tdx = _axis_setup(ax, bx)
    sys_, ry, tmy, tdy = _axis_setup(ay, by)
    szs, rz, tmz, tdz = _axis_setup(az, bz)
    stride_x = shape[1] * shape[2]
    stride_y = shape[2]
    ix, iy, iz = int(np.floor(ax)), int(np.floor(ay)), int(np.floor(az))
    idx = (ix * shape[1] + iy) * shape[2] + iz
    length = max(np.sqrt((bx - ax) ** 2 + (by - ay) ** 2 + (bz - az) ** 2), 1e-12)
    ux, uy, uz = (bx - ax) / length, (by - ay) / length, (bz - az) / length
    t_enter = 0.0
    n_steps = rx + ry + rz
    for _ in range(n_steps):
        is_hit = hit and t_enter > hit_from_t
        if is_hit or not _grazes(cells, box_lo, ix, iy, iz, ux, uy, uz, graze_sin):
            _visit(target, idx, is_hit, mode, inc, dec)
        if rx > 0 and (ry == 0 or tmx <= tmy) and (rz == 0 or tmx <= tmz):
            t_enter = tmx
            tmx += tdx
            idx += sxs * stride_x
            ix += sxs
            rx -= 1
        elif ry > 0 and (rz == 0 or tmy <= tmz):
            t_enter = tmy
            tmy += tdy
            idx += sys_ * stride_y
            iy += sys_
            ry -= 1
        else:
            t_enter = tmz
            tmz += tdz
            idx += szs
            iz += szs
            rz -= 1
    _visit(target, idx, hit, mode, inc, dec)
    return n_steps + 1


@nb.njit(inline="always")
def _walk_bresenham(target, shape, ax, ay, az, bx, by, bz, hit, hit_from_t, mode, inc, dec, cells, box_lo,
                    graze_sin):
    """3D Bresenham between the centres of the cells holding a and b: one cell per step of the
    axis with the largest extent, minor axes rounded to the nearest cell (integer error terms,
    branch-free). Cells past hit_from_t (and the end cell) are hits when `hit`; a miss leaves the
    occupied cells the line between those centres only grazes alone (_grazes: the path and what it
    does depend on the two cells alone, so rays ending in one cell share it)."""
    x0, y0, z0 = int(np.floor(ax)), int(np.floor(ay)), int(np.floor(az))
    dx, dy, dz = int(np.floor(bx)) - x0, int(np.floor(by)) - y0, int(np.floor(bz)) - z0
    adx, ady, adz = abs(dx), abs(dy), abs(dz)
    n = max(adx, ady, adz)
    stride_x = shape[1] * shape[2]
    stride_y = shape[2]
    idx = (x0 * shape[1] + y0) * shape[2] + z0
    if n == 0:
        _visit(target, idx, hit, mode, inc, dec)
        return 1
    ux = 1 if dx > 0 else -1
    uy = 1 if dy > 0 else -1
    uz = 1 if dz > 0 else -1
    sx = ux * stride_x
    sy = uy * stride_y
    sz = uz
    inv = 1.0 / np.sqrt(dx * dx + dy * dy + dz * dz)
    lx, ly, lz = dx * inv, dy * inv, dz * inv
    n2 = 2 * n
    # Offset along an axis after k steps is round(k * |d| / n): accumulate 2|d| per step from n,
    # and move one cell each time the accumulator passes 2n (at most once per step, |d| <= n).
    ex, ey, ez = n, n, n
    first_hit = int(np.floor(hit_from_t * n)) + 1 if hit else n + 1
    ix, iy, iz = x0, y0, z0
    for k in range(n):
        if k >= first_hit or not _grazes(cells, box_lo, ix, iy, iz, lx, ly, lz, graze_sin):
            _visit(target, idx, k >= first_hit, mode, inc, dec)
        ex += 2 * adx
        ey += 2 * ady
        ez += 2 * adz
        cx = ex >= n2
        cy = ey >= n2
        cz = ez >= n2
        idx += cx * sx + cy * sy + cz * sz
        ix += cx * ux
        iy += cy * uy
        iz += cz * uz
        ex -= cx * n2
        ey -= cy * n2
        ez -= cz * n2
    _visit(target, idx, hit, mode, inc, dec)
    return n + 1


@nb.njit(**_JIT)
def trace_rows(depth, scale, slope_x, slope_y, row_lo, row_hi, rot, origin_c, inv_res,
               min_range, max_range, far_limit, hit_depth, shape, target, mode, traversal, inc, dec,
               cells, box_lo, graze_sin, counts):
    """Walk the rays of image rows [row_lo, row_hi) into `target` (a flat box of `shape` cells;
    origin_c is the sensor origin in that box's continuous cell coordinates). Depths in
    min_range..far_limit are rays; those longer than max_range are cut there, all misses. cells is
    the grid as it stood before the frame, box cell k being its cell k + box_lo: a ray leaves alone
    the occupied cells it only grazes (graze_sin, _grazes; 0 clears them like any other)."""
    w = depth.shape[1]
    ox, oy, oz = origin_c[0], origin_c[1], origin_c[2]
    for v in range(row_lo, row_hi):
        sy = slope_y[v]
        for u in range(w):
            z = depth[v, u] * scale
            if not (z >= min_range and z <= far_limit):
                counts[COUNT_INVALID] += 1
                continue
            x = slope_x[u] * z
            y = sy * z
            length = np.sqrt(x * x + y * y + z * z)
            hit = True
            f = inv_res
            if length > max_range:
                f = inv_res * max_range / length
                length = max_range
                hit = False
                counts[COUNT_TRUNCATED] += 1
            bx = ox + (rot[0, 0] * x + rot[0, 1] * y + rot[0, 2] * z) * f
            by = oy + (rot[1, 0] * x + rot[1, 1] * y + rot[1, 2] * z) * f
            bz = oz + (rot[2, 0] * x + rot[2, 1] * y + rot[2, 2] * z) * f
            hit_from_t = 1.0 - hit_depth / length
            if traversal == TRAVERSAL_BRESENHAM and mode == MODE_MARK and hit_depth == 0.0:
                # The Bresenham path depends only on the origin and end cells: a ray ending in a
                # cell a walk already ended in would mark exactly the same cells again.
                end = (int(np.floor(bx)) * shape[1] + int(np.floor(by))) * shape[2] + int(np.floor(bz))
                if target[end] & MARK_WALKED:
                    target[end] |= MARK_HIT if hit else MARK_MISS
                    counts[COUNT_RAYS] += 1
                    continue
                target[end] |= MARK_WALKED
            if traversal == TRAVERSAL_BRESENHAM:
                counts[COUNT_VISITS] += _walk_bresenham(target, shape, ox, oy, oz, bx, by, bz, hit,
                                                        hit_from_t, mode, inc, dec, cells, box_lo, graze_sin)
            else:
                counts[COUNT_VISITS] += _walk(target, shape, ox, oy, oz, bx, by, bz, hit, hit_from_t,
                                              mode, inc, dec, cells, box_lo, graze_sin)
            counts[COUNT_RAYS] += 1


@nb.njit(**_JIT)
def apply_marks(cells, box_lo, marks, box_shape, x_lo, x_hi, inc, dec):
    """One HIMM update per marked cell of the box slab x in [x_lo, x_hi); marks is (threads, n),
    combined by OR (hit over miss). Returns (cells updated, hits)."""
    bsy, bsz = box_shape[1], box_shape[2]
    n_threads = marks.shape[0]
    updated = 0
    hits = 0
    for x in range(x_lo, x_hi):
        for y in range(bsy):
            base = (x * bsy + y) * bsz
            for z in range(bsz):
                m = marks[0, base + z]
                for k in range(1, n_threads):
                    m |= marks[k, base + z]
                if m & (MARK_HIT | MARK_MISS) == 0:
                    continue
                gx, gy, gz = box_lo[0] + x, box_lo[1] + y, box_lo[2] + z
                c = cells[gx, gy, gz]
                if c == INACCESSIBLE:
                    continue
                if c == UNKNOWN:
                    c = P_PRIOR
                if m & MARK_HIT:
                    c = min(c + inc, P_MAX)
                    hits += 1
                else:
                    c = max(c - dec, P_MIN)
                cells[gx, gy, gz] = c
                updated += 1
    return updated, hits


@nb.njit(inline="always")
def _agreed_value(cells, x, y, z, threshold):
    """Mean of the six neighbours if all are free or all occupied, else UNKNOWN."""
    total = 0
    n_occ = 0
    for d in range(6):
        nx, ny, nz = x, y, z
        if d == 0:
            nx -= 1
        elif d == 1:
            nx += 1
        elif d == 2:
            ny -= 1
        elif d == 3:
            ny += 1
        elif d == 4:
            nz -= 1
        else:
            nz += 1
        v = cells[nx, ny, nz]
        if v < P_MIN:
            return UNKNOWN
        total += v
        if v >= threshold:
            n_occ += 1
    if n_occ != 0 and n_occ != 6:
        return UNKNOWN
    return (total + 3) // 6


@nb.njit(**_JIT)
def gap_fill(cells, lo, hi, threshold):
    """Fill isolated unknown cells in the inclusive array box lo..hi (thesis §6.3, last
    paragraph). Candidates are found first and written after, so no fill feeds another."""
    mx, my, mz = cells.shape
    x0, y0, z0 = max(lo[0], 1), max(lo[1], 1), max(lo[2], 1)
    x1, y1, z1 = min(hi[0], mx - 2), min(hi[1], my - 2), min(hi[2], mz - 2)
    count = 0
    for x in range(x0, x1 + 1):
        for y in range(y0, y1 + 1):
            for z in range(z0, z1 + 1):
                if cells[x, y, z] == UNKNOWN and _agreed_value(cells, x, y, z, threshold) != UNKNOWN:
                    count += 1
    if count == 0:
        return 0
    found = np.empty((count, 4), dtype=np.int64)
    k = 0
    for x in range(x0, x1 + 1):
        for y in range(y0, y1 + 1):
            for z in range(z0, z1 + 1):
                if cells[x, y, z] == UNKNOWN:
                    v = _agreed_value(cells, x, y, z, threshold)
                    if v != UNKNOWN:
                        found[k, 0], found[k, 1], found[k, 2], found[k, 3] = x, y, z, v
                        k += 1
    for i in range(count):
        cells[found[i, 0], found[i, 1], found[i, 2]] = found[i, 3]
    return count

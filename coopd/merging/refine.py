"""Refinement of a transform on the full-resolution grids: ICP between occupied cell centres, then a
sub-cell fit on distance fields of a's surfaces.

Point-to-point ICP with a shrinking correspondence radius (from six cells down to 1.5, then held),
6 DoF so that small roll/pitch differences between drones are absorbed. Between two lattices of cell
centres it has a local minimum at every whole-cell slide along a wall (every wall cell finds a
partner at distance 0; only edges pull back), so it can stop a cell away from the truth even on a
lossless copy; and where one map saw a wall from one side and the other map from the other side, it
pairs the two sides and pulls them together. `field_fit` then moves b's occupied cells (6 DoF,
Levenberg-Marquardt) onto the trilinearly interpolated distance to a's occupied cells that face the
same way (their free side), where a slide along a wall is continuous and opposite sides of a wall
never pair.
"""

from dataclasses import dataclass
from functools import cached_property

import numba as nb
import numpy as np

from coopd.kernel_cache import CACHE as KERNEL_CACHE

from ..geometry import apply
from ..grid.kernels import free_side
from .mtm import kabsch

_JIT = {"nogil": True, "cache": KERNEL_CACHE}


@nb.njit(**_JIT)
def cube_count(sums, cx, cy, cz, s):
    """Occupied cells in the cube of half-size s around cell (cx, cy, cz), clipped to the grid, from
    the wrapping uint16 prefix sums of search_index (exact: the cube holds fewer than 2^16 cells)."""
    mx, my, mz = sums.shape[0] - 1, sums.shape[1] - 1, sums.shape[2] - 1
    x0, y0, z0 = max(cx - s, 0), max(cy - s, 0), max(cz - s, 0)
    x1, y1, z1 = min(cx + s + 1, mx), min(cy + s + 1, my), min(cz + s + 1, mz)
    if x0 >= x1 or y0 >= y1 or z0 >= z1:
        return 0
    total = (np.int64(sums[x1, y1, z1]) - np.int64(sums[x0, y1, z1]) - np.int64(sums[x1, y0, z1])
             - np.int64(sums[x1, y1, z0]) + np.int64(sums[x0, y0, z1]) + np.int64(sums[x0, y1, z0])
             + np.int64(sums[x1, y0, z0]) - np.int64(sums[x0, y0, z0]))
    return total & 0xFFFF


@nb.njit(**_JIT)
def _nearest_cells(occupied, sums, columns, offset, points, inv_res, max_cells, out_idx, out_dist, sides,
                   want):
    """Nearest occupied cell of each point whose side bits (sides, per cell) meet the point's (want,
    per point; ANY_SIDE takes every occupied cell) within max_cells, searched in shells of
    growing Chebyshev radius around the point's cell until no farther shell can hold a nearer one.
    Until a first occupied cell is met, a shell whose whole cube is empty (prefix sums) is skipped
    unvisited, and so is every column of a shell's side that holds no occupied cell in its z range
    (column bits): the same answer, in the same order, without walking empty space cell by cell."""
    mx, my, mz = occupied.shape
    for p in range(points.shape[0]):
        kx = points[p, 0] * inv_res - offset[0]
        ky = points[p, 1] * inv_res - offset[1]
        kz = points[p, 2] * inv_res - offset[2]
        cx, cy, cz = int(np.floor(kx + 0.5)), int(np.floor(ky + 0.5)), int(np.floor(kz + 0.5))
        best = np.inf
        bx = by = bz = -1
        s = 0
        while True:
            bound = max(0.0, s - 0.5)  # the point lies within half a cell of its cell's centre
            if bound > max_cells or bound * bound >= best:
                break
            if best == np.inf and s <= MAX_CUBE_HALF and cube_count(sums, cx, cy, cz, s) == 0:
                s += 1
                continue
            for dx in range(-s, s + 1):
                x = cx + dx
                if x < 0 or x >= mx:
                    continue
                for dy in range(-s, s + 1):
                    y = cy + dy
                    if y < 0 or y >= my:
                        continue
                    edge = dx == -s or dx == s or dy == -s or dy == s
                    if edge and not column_holds(columns, x, y, cz - s, cz + s):
                        continue
                    step = 1 if edge else max(1, 2 * s)
                    for dz in range(-s, s + 1, step):
                        z = cz + dz
                        if z < 0 or z >= mz or not occupied[x, y, z] or not sides[x, y, z] & want[p]:
                            continue
                        d = (x - kx) ** 2 + (y - ky) ** 2 + (z - kz) ** 2
                        if d < best:
                            best, bx, by, bz = d, x, y, z
            s += 1
        if best <= max_cells * max_cells:
            out_dist[p] = np.sqrt(best)
            out_idx[p, 0], out_idx[p, 1], out_idx[p, 2] = bx, by, bz
        else:
            out_dist[p] = np.inf


@nb.njit(**_JIT)
def column_holds(bits, x, y, z0, z1):
    """Whether column (x, y) of search_index's bits holds an occupied cell with z0 <= z <= z1 (clipped)."""
    z0 = max(z0, 0)
    z1 = min(z1, bits.shape[2] * 64 - 1)
    if z0 > z1:
        return False
    for w in range(z0 // 64, z1 // 64 + 1):
        lo = max(z0 - 64 * w, 0)
        hi = min(z1 - 64 * w, 63)
        below_hi = np.uint64(0xFFFFFFFFFFFFFFFF) >> np.uint64(63 - hi)
        below_lo = (np.uint64(1) << np.uint64(lo)) - np.uint64(1)
        mask = below_hi & ~below_lo
        if bits[x, y, w] & mask:
            return True
    return False


MAX_CUBE_HALF = 19
"""Largest half-size of a cube counted by cube_count: (2 * 19 + 1)^3 < 2^16 cells."""


@nb.njit(**_JIT)
def search_index(occupied):
    """What the nearest-cell search skips empty space with, from one scan of a 3-D mask:
    - prefix sums (shape + 1 per axis, uint16 wrapping): any box's count by inclusion-exclusion,
      exact modulo 2^16 (cube_count), each slice's sums built on the previous one's;
    - column bits (mx, my, words) uint64: bit z % 64 of word z // 64 says whether (x, y, z) is
      occupied (column_holds)."""
    mx, my, mz = occupied.shape
    sums = np.zeros((mx + 1, my + 1, mz + 1), dtype=np.uint16)
    bits = np.zeros((mx, my, max(1, (mz + 63) // 64)), dtype=np.uint64)
    for x in range(mx):
        for y in range(my):
            row = 0
            for z in range(mz):
                if occupied[x, y, z]:
                    row += 1
                    bits[x, y, z // 64] |= np.uint64(1) << np.uint64(z % 64)
                below = sums[x, y + 1, z + 1] + sums[x + 1, y, z + 1] - sums[x, y, z + 1]
                sums[x + 1, y + 1, z + 1] = below + row
    return sums, bits


@dataclass(frozen=True)
class OccupiedCells:
    """A grid's occupied cells for nearest-neighbour queries: ICP's target. Cell centres lie on a
    lattice, so the nearest one is found by visiting the cells around a point, nearest shell first; a
    k-d tree over a lattice is slow (every query meets many equidistant points)."""

    occupied: np.ndarray
    offset: np.ndarray
    resolution: float
    sides: np.ndarray | None = None
    """Per cell, the bits (1 << side, SIDES) of the sides it was seen from (facing_bits), or None:
    then they come from cells, or every occupied cell pairs with any point."""
    cells: np.ndarray | None = None
    threshold: int = 0
    """The grid's cells and occupied threshold, when side bits are made from them on the first query
    that needs them (a map that is only ever b never pays for them)."""

    @cached_property
    def side_bits(self) -> np.ndarray:
        """sides, or facing_bits of cells, or ANY_SIDE for every occupied cell."""
        if self.sides is not None:
            return self.sides
        if self.cells is not None:
            return facing_bits(self.cells, self.threshold)
        return np.where(self.occupied, ANY_SIDE, 0).astype(np.uint8)

    @cached_property
    def index(self) -> tuple[np.ndarray, np.ndarray]:
        """search_index of the occupied cells, made on the first query (2 bytes and a bit a cell)."""
        return search_index(self.occupied)

    def nearest(self, points: np.ndarray, radius: float,
                want: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(within, centres): which points have an occupied cell centre within radius (metres), and
        the nearest such centre of each (rows of the others are undefined); with want (side bits per
        point), only cells seen from one of the point's sides count."""
        points = np.ascontiguousarray(points, dtype=np.float64)
        idx = np.empty((len(points), 3), dtype=np.int64)
        dist = np.empty(len(points))
        want = np.full(len(points), ANY_SIDE, dtype=np.uint8) if want is None else want
        _nearest_cells(self.occupied, *self.index, np.asarray(self.offset, dtype=np.int64), points,
                       1.0 / self.resolution, radius / self.resolution, idx, dist, self.side_bits,
                       np.ascontiguousarray(want, dtype=np.uint8))
        return np.isfinite(dist), (idx + self.offset) * self.resolution


@nb.njit(**_JIT)
def _icp_step(occupied, sums, columns, offset, resolution, source, moved, max_cells, idx, dist, previous,
              has_previous, min_pairs, sides, want):
    """One ICP step: the nearest occupied cell of each moved point within max_cells, then (count of
    points with one, same pairs as `previous`, the rigid fit of those pairs). The fit is computed only
    when there are at least min_pairs pairs and they changed; previous (the last pairs' cells, -1 rows
    for points without one) is updated then."""
    _nearest_cells(occupied, sums, columns, offset, moved, 1.0 / resolution, max_cells, idx, dist, sides,
                   want)
    n = 0
    same = has_previous
    for p in range(moved.shape[0]):
        within = np.isfinite(dist[p])
        n += within
        for a in range(3):
            cell = idx[p, a] if within else -1
            if previous[p, a] != cell:
                same = False
    t = np.eye(4)
    if n < min_pairs or same:
        return n, same, t
    src = np.empty((n, 3))
    dst = np.empty((n, 3))
    k = 0
    for p in range(moved.shape[0]):
        within = np.isfinite(dist[p])
        for a in range(3):
            previous[p, a] = idx[p, a] if within else -1
        if within:
            for a in range(3):
                src[k, a] = source[p, a]
                dst[k, a] = (idx[p, a] + offset[a]) * resolution
            k += 1
    return n, same, kabsch(src, dst)


ICP_MIN_PAIRS = 10
"""ICP stops when fewer points than this have a partner within the radius."""


def icp(target: OccupiedCells, source: np.ndarray, t0: np.ndarray, iterations: int,
        normals: np.ndarray | None = None) -> tuple[np.ndarray, float]:
    """(refined T, inlier fraction): source points (b frame) pulled onto the target's occupied cell
    centres (a frame). Each step pairs every point with the nearest centre within a radius that
    shrinks from 6 to 1.5 cells over the first half of the steps and is then held; unchanged pairs
    skip the fit, and end the refinement under the held radius (every further step would repeat).
    With the source points' free-side normals (free_sides) and the target's side bits, a point pairs
    only with cells seen from the side it was seen from: the two sides of a wall, each seen by one
    map, are not pulled together."""
    t = np.asarray(t0, dtype=np.float64).copy()
    coarse = max(1, iterations // 2)
    held = np.full(max(0, iterations - coarse), 1.5)
    radii = np.concatenate([np.geomspace(6.0, 1.5, coarse), held]) * target.resolution
    points = np.ascontiguousarray(source, dtype=np.float64)
    offset = np.asarray(target.offset, dtype=np.int64)
    idx = np.empty((len(source), 3), dtype=np.int64)
    dist = np.empty(len(source))
    previous = np.empty((len(source), 3), dtype=np.int64)
    frac = 0.0
    has_previous = False
    want = np.full(len(source), ANY_SIDE, dtype=np.uint8)
    if normals is not None:
        normals = np.ascontiguousarray(normals, dtype=np.float64)
    for k, r in enumerate(radii):
        moved = np.ascontiguousarray(apply(t, source))
        if normals is not None:
            _side_bits_into(normals, np.ascontiguousarray(t[:3, :3]), want)
        n, same, fitted = _icp_step(target.occupied, *target.index, offset,
                                    float(target.resolution), points, moved, r / target.resolution, idx, dist,
                                    previous, has_previous, ICP_MIN_PAIRS, target.side_bits, want)
        frac = n / len(source) if len(source) else 0.0
        if n < ICP_MIN_PAIRS:
            break
        if same:
            if k >= coarse:  # same pairs under the held radius: every further step repeats this one
                break
            continue  # same pairs, same estimate
        has_previous = True
        t = fitted
    return t, frac


FIELD_CELLS = 3
"""Distances in the field fit's distance fields are clipped at this many cells: a point farther from
a's surfaces than that is outside the overlap and pulls nothing."""
FACING_MIN = 0.38
"""A surface cell faces one of the six axis directions when its free-side normal has at least this
component along it (cos 67.5 deg: a wall diagonal to the lattice faces two)."""
SIDES = 6
"""+x, -x, +y, -y, +z, -z."""
TUKEY_CELLS = (4.0, 2.0, 1.5)
"""Scales (cells) of the field fit's Tukey weights, one pass each: wide first, then down to the
noise of two maps' surfaces."""
FIELD_SCALE = 64
"""Distance fields are stored in 1/FIELD_SCALE cell (uint8; 1.6 mm at 0.1 m cells)."""


@nb.njit(**_JIT)
def free_sides(cells, threshold, offset, res, points):
    """Free-side normal (unit, or zeros) of the occupied cell under each point (metres, grid frame)."""
    out = np.zeros((points.shape[0], 3))
    mx, my, mz = cells.shape
    for p in range(points.shape[0]):
        x = int(np.floor(points[p, 0] / res + 0.5)) - offset[0]
        y = int(np.floor(points[p, 1] / res + 0.5)) - offset[1]
        z = int(np.floor(points[p, 2] / res + 0.5)) - offset[2]
        if 0 <= x < mx and 0 <= y < my and 0 <= z < mz and cells[x, y, z] >= threshold:
            out[p] = free_side(cells, threshold, x, y, z)
    return out


@nb.njit(**_JIT)
def facing_fields(cells, threshold, lo, shape, max_cells):
    """Per side (SIDES), the distance in cells from each cell of the box [lo, lo + shape) of the grid
    to the nearest centre of an occupied cell facing that side (its free-side normal has at least
    FACING_MIN along it: which side of a wall the map saw it from), clipped at max_cells; uint8 in
    units of 1/FIELD_SCALE cell. Occupied cells just outside the box count too. Each occupied cell
    stamps its distance into the ball of max_cells around it: the cost follows the surfaces, not the
    volume of the box."""
    r = int(np.ceil(max_cells))
    offsets = []
    for dx in range(-r, r + 1):
        for dy in range(-r, r + 1):
            for dz in range(-r, r + 1):
                dist = np.sqrt(dx * dx + dy * dy + dz * dz)
                if dist <= max_cells:
                    offsets.append((dx, dy, dz, np.uint8(round(dist * FIELD_SCALE))))
    clip = np.uint8(round(max_cells * FIELD_SCALE))
    out = np.full((SIDES, shape[0], shape[1], shape[2]), clip, dtype=np.uint8)
    mx, my, mz = cells.shape
    for x in range(max(0, lo[0] - r), min(mx, lo[0] + shape[0] + r)):
        for y in range(max(0, lo[1] - r), min(my, lo[1] + shape[1] + r)):
            for z in range(max(0, lo[2] - r), min(mz, lo[2] + shape[2] + r)):
                if cells[x, y, z] < threshold:
                    continue
                n = free_side(cells, threshold, x, y, z)
                for a in range(3):
                    if n[a] >= FACING_MIN:
                        side = 2 * a
                    elif n[a] <= -FACING_MIN:
                        side = 2 * a + 1
                    else:
                        continue
                    for dx, dy, dz, dist in offsets:
                        i, j, k = x + dx - lo[0], y + dy - lo[1], z + dz - lo[2]
                        if 0 <= i < shape[0] and 0 <= j < shape[1] and 0 <= k < shape[2] \
                                and dist < out[side, i, j, k]:
                            out[side, i, j, k] = dist
    return out


@nb.njit(**_JIT)
def _field_normal_equations(fields, keys, sides, centre, res, tukey_cells, max_cells):
    """Gauss-Newton normal equations (H 6x6, g 6), robust cost and points used, of the residuals
    d(q) = fields[side] at q = keys (fractional cell indices of the moved points), trilinear, with a
    left twist (rotation about centre, translation) as unknowns and Tukey weights of scale
    tukey_cells; points with no side (-1), outside the fields or at their clip distance are left out.
    Residuals and lever arms in metres."""
    _, mx, my, mz = fields.shape
    h = np.zeros((6, 6))
    g = np.zeros(6)
    j = np.zeros(6)
    cost = 0.0
    used = 0
    c2 = tukey_cells * tukey_cells
    inv_scale = 1.0 / FIELD_SCALE
    for p in range(keys.shape[0]):
        s = sides[p]
        if s < 0:
            continue
        x, y, z = keys[p, 0], keys[p, 1], keys[p, 2]
        x0, y0, z0 = int(np.floor(x)), int(np.floor(y)), int(np.floor(z))
        if x0 < 0 or y0 < 0 or z0 < 0 or x0 + 1 >= mx or y0 + 1 >= my or z0 + 1 >= mz:
            continue
        fx, fy, fz = x - x0, y - y0, z - z0
        d = 0.0
        gx = gy = gz = 0.0
        for a in range(2):
            wa = fx if a else 1.0 - fx
            da = 1.0 if a else -1.0
            for b in range(2):
                wb = fy if b else 1.0 - fy
                db = 1.0 if b else -1.0
                for c in range(2):
                    wc = fz if c else 1.0 - fz
                    dc = 1.0 if c else -1.0
                    v = fields[s, x0 + a, y0 + b, z0 + c] * inv_scale
                    d += wa * wb * wc * v
                    gx += da * wb * wc * v
                    gy += wa * db * wc * v
                    gz += wa * wb * dc * v
        if d >= max_cells - 1e-6:
            continue
        u = d * d / c2
        if u >= 1.0:
            cost += c2 / 6.0
            continue
        w = (1.0 - u) * (1.0 - u)
        cost += c2 / 6.0 * (1.0 - (1.0 - u) ** 3)
        used += 1
        r = d * res
        qx = keys[p, 0] * res - centre[0]
        qy = keys[p, 1] * res - centre[1]
        qz = keys[p, 2] * res - centre[2]
        j[0] = qy * gz - qz * gy
        j[1] = qz * gx - qx * gz
        j[2] = qx * gy - qy * gx
        j[3], j[4], j[5] = gx, gy, gz
        for s1 in range(6):
            g[s1] += w * j[s1] * r
            for s2 in range(6):
                h[s1, s2] += w * j[s1] * j[s2]
    return h, g, cost, used


def _twist(xi: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """The rigid motion of a twist: rotation by xi[:3] (axis-angle) about centre, then xi[3:]."""
    angle = float(np.linalg.norm(xi[:3]))
    r = np.eye(3)
    if angle > 1e-12:
        k = xi[:3] / angle
        kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
        r = np.eye(3) + np.sin(angle) * kx + (1.0 - np.cos(angle)) * kx @ kx
    out = np.eye(4)
    out[:3, :3] = r
    out[:3, 3] = centre - r @ centre + xi[3:]
    return out


ANY_SIDE = (1 << SIDES) - 1
"""Side bits of a cell or point with no free side: it pairs with any."""


@nb.njit(**_JIT)
def facing_bits(cells, threshold):
    """Per cell, the bits (1 << side) of the SIDES its free-side normal has at least FACING_MIN along
    (one, or two or three for a diagonal surface); ANY_SIDE for an occupied cell with no free side,
    0 for cells not occupied: what icp pairs a point seen from a side with."""
    mx, my, mz = cells.shape
    out = np.zeros(cells.shape, dtype=np.uint8)
    for x in range(mx):
        for y in range(my):
            for z in range(mz):
                if cells[x, y, z] < threshold:
                    continue
                n = free_side(cells, threshold, x, y, z)
                bits = 0
                for a in range(3):
                    if n[a] >= FACING_MIN:
                        bits |= 1 << (2 * a)
                    elif n[a] <= -FACING_MIN:
                        bits |= 1 << (2 * a + 1)
                out[x, y, z] = bits if bits else ANY_SIDE
    return out


@nb.njit(**_JIT)
def _side_bits_into(normals, rotation, out):
    """out[i] = facing_bits of normal i turned by rotation (ANY_SIDE for a zero normal)."""
    for i in range(normals.shape[0]):
        bits = 0
        for a in range(3):
            n = normals[i]
            c = rotation[a, 0] * n[0] + rotation[a, 1] * n[1] + rotation[a, 2] * n[2]
            if c >= FACING_MIN:
                bits |= 1 << (2 * a)
            elif c <= -FACING_MIN:
                bits |= 1 << (2 * a + 1)
        zero = normals[i, 0] == 0.0 and normals[i, 1] == 0.0 and normals[i, 2] == 0.0
        out[i] = ANY_SIDE if zero or bits == 0 else bits


def side_bits(normals: np.ndarray, rotation: np.ndarray) -> np.ndarray:
    """facing_bits of points from their free-side normals (b frame) turned by rotation into a's frame;
    ANY_SIDE for a point with none."""
    out = np.empty(len(normals), dtype=np.uint8)
    _side_bits_into(np.ascontiguousarray(normals, dtype=np.float64),
                    np.ascontiguousarray(rotation, dtype=np.float64), out)
    return out


def side_of(normals: np.ndarray, rotation: np.ndarray) -> np.ndarray:
    """Which of the SIDES each free-side normal (b frame) faces once turned into a's frame; -1 for none."""
    n = normals @ np.asarray(rotation).T
    signed = np.concatenate([n, -n], axis=1)[:, [0, 3, 1, 4, 2, 5]]
    out = np.argmax(signed, axis=1)
    out[np.abs(normals).sum(axis=1) == 0] = -1
    return out.astype(np.int64)


@dataclass(frozen=True)
class FieldFit:
    """field_fit's result: the transform and how well b's surfaces lie on a's under it."""

    transform: np.ndarray
    used: int
    """Points within FIELD_CELLS of a same-facing surface of a (the overlap the fit rests on)."""
    rms_m: float
    """Robust (Tukey) root mean square distance of those points to a's surfaces, metres."""


def field_fit(target_cells: np.ndarray, target_offset: np.ndarray, resolution: float, threshold: int,
              source: np.ndarray, source_normals: np.ndarray, t: np.ndarray, iterations: int = 12,
              tukey_cells=TUKEY_CELLS, max_step_cells: float = 0.5) -> FieldFit:
    """Sub-cell 6-DoF refinement: Levenberg-Marquardt on the distance (trilinear) from the moved
    source points (b's occupied cells, metres) to the centres of a's occupied cells that face the
    same way (source_normals: their free-side normals, see free_sides), Tukey-weighted at each scale
    of tukey_cells in turn (wide first, so that a start a cell or two off is still drawn in); a point
    beyond FIELD_CELLS of any such cell (outside the overlap) does not count. Facing matters: where
    one map saw a wall from one side and the other from the other, the unsigned distance pulls the
    two sides together. Each step is held within max_step_cells at the points' extent and taken
    only when it lowers the cost, and the result is t itself unless it fits better at the last
    scale: the fit never makes t worse by its own measure."""
    t = np.asarray(t, dtype=np.float64).copy()
    source = np.ascontiguousarray(source, dtype=np.float64)
    offset = np.asarray(target_offset, dtype=np.int64)
    none = FieldFit(t, 0, float("inf"))
    if len(source) == 0 or not (np.all(np.isfinite(t)) and np.all(np.isfinite(source))):
        return none
    keys = apply(t, source) / resolution - offset
    if not np.all(np.isfinite(keys)):
        return none
    margin = FIELD_CELLS + 2
    shape = np.array(target_cells.shape)
    lo = np.maximum(np.floor(keys.min(axis=0)).astype(np.int64) - margin, 0)
    hi = np.minimum(np.ceil(keys.max(axis=0)).astype(np.int64) + margin + 1, shape)
    if np.any(hi - lo < 2):
        return none
    fields = facing_fields(target_cells, threshold, lo, hi - lo, float(FIELD_CELLS))
    origin = (lo + offset) * resolution  # metres of the fields' cell [0, 0, 0]
    sides = side_of(np.asarray(source_normals, dtype=np.float64), t[:3, :3])

    def normal_equations(tt, tukey):
        moved = apply(tt, source)
        k = np.ascontiguousarray(moved / resolution - offset - lo)
        centre = moved.mean(axis=0)
        h, g, cost, used = _field_normal_equations(fields, k, sides, centre - origin, resolution, tukey,
                                                   float(FIELD_CELLS))
        return h, g, cost, used, centre

    scales = np.atleast_1d(np.asarray(tukey_cells, dtype=np.float64))
    extent = max(float(np.abs(apply(t, source) - apply(t, source).mean(axis=0)).max()), resolution)
    start = t
    for tukey in scales:
        t = _levenberg_marquardt(lambda tt, k=tukey: normal_equations(tt, k), t, iterations,
                                 extent, max_step_cells * resolution)
    _, _, cost, used, _ = normal_equations(t, scales[-1])
    _, _, start_cost, start_used, _ = normal_equations(start, scales[-1])
    if start_cost <= cost:
        t, cost, used = start, start_cost, start_used
    counted = int(np.sum(sides >= 0))
    rms = float(np.sqrt(6.0 * cost / max(1, counted))) * resolution if used else float("inf")
    return FieldFit(t, int(used), rms)


def _levenberg_marquardt(normal_equations, t: np.ndarray, iterations: int, extent: float,
                         limit: float) -> np.ndarray:
    """t improved by damped Gauss-Newton steps (left twists about the points' centre) on
    normal_equations(t) -> (H, g, cost, used, centre); a step reaches at most limit metres at the
    points' extent and is kept only when it lowers the cost."""
    h, g, cost, used, centre = normal_equations(t)
    damping = 1e-3
    for _ in range(iterations):
        if used < 6:
            break
        scale = np.sqrt(np.maximum(np.diag(h), 1e-12))
        try:
            step = -np.linalg.solve(h + damping * np.diag(scale ** 2) + 1e-12 * np.eye(6), g)
        except np.linalg.LinAlgError:
            break
        reach = np.linalg.norm(step[:3]) * extent + np.linalg.norm(step[3:])
        if reach > limit:
            step *= limit / reach
        trial = _twist(step, centre) @ t
        h2, g2, cost2, used2, centre2 = normal_equations(trial)
        if cost2 < cost:
            t, h, g, cost, used, centre = trial, h2, g2, cost2, used2, centre2
            damping = max(damping / 3.0, 1e-6)
            if reach < 0.05 * limit:
                break
        else:
            damping *= 4.0
            if damping > 1e4:
                break
    return t

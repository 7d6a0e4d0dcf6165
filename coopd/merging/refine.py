"""Refinement of a transform on the full-resolution grids: ICP between occupied cell centres, then a
sub-cell shift on a smoothed surface.

Point-to-point ICP with a shrinking correspondence radius (from six cells down to 1.5, then held),
6 DoF so that small roll/pitch differences between drones are absorbed. Between two lattices of cell
centres it has a local minimum at every whole-cell slide along a wall (every wall cell finds a
partner at distance 0; only edges pull back), so it can stop a cell away from the truth even on a
lossless copy. `subcell_shift` then moves the result by the translation, within +-1 cell in quarter
cells, that puts the moved points highest on a Gaussian-smoothed image of the target's occupied
cells, where sliding along a wall changes nothing and edges and corners decide.
"""

from dataclasses import dataclass

import numba as nb
import numpy as np

from coopd.kernel_cache import CACHE as KERNEL_CACHE

from ..geometry import apply
from .mtm import estimate
from .preprocess import gaussian

_JIT = {"nogil": True, "cache": KERNEL_CACHE}
SUBCELL_STEPS = np.arange(-4, 5) / 4.0
"""Shifts tried per axis by subcell_shift, in cells."""


@nb.njit(**_JIT)
def _nearest_cells(occupied, offset, points, inv_res, max_cells, out_idx, out_dist):
    """Nearest occupied cell of each point (cell-index units) within max_cells, searched in shells of
    growing Chebyshev radius around the point's cell until no farther shell can hold a nearer one."""
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
            for dx in range(-s, s + 1):
                x = cx + dx
                if x < 0 or x >= mx:
                    continue
                for dy in range(-s, s + 1):
                    y = cy + dy
                    if y < 0 or y >= my:
                        continue
                    edge = dx == -s or dx == s or dy == -s or dy == s
                    step = 1 if edge else max(1, 2 * s)
                    for dz in range(-s, s + 1, step):
                        z = cz + dz
                        if z < 0 or z >= mz or not occupied[x, y, z]:
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


@dataclass(frozen=True)
class OccupiedCells:
    """A grid's occupied cells for nearest-neighbour queries: ICP's target. Cell centres lie on a
    lattice, so the nearest one is found by visiting the cells around a point, nearest shell first; a
    k-d tree over a lattice is slow (every query meets many equidistant points)."""

    occupied: np.ndarray
    offset: np.ndarray
    resolution: float

    def nearest(self, points: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray]:
        """(within, centres): which points have an occupied cell centre within radius (metres), and
        the nearest such centre of each (rows of the others are undefined)."""
        points = np.ascontiguousarray(points, dtype=np.float64)
        idx = np.empty((len(points), 3), dtype=np.int64)
        dist = np.empty(len(points))
        _nearest_cells(self.occupied, np.asarray(self.offset, dtype=np.int64), points, 1.0 / self.resolution,
                       radius / self.resolution, idx, dist)
        return np.isfinite(dist), (idx + self.offset) * self.resolution


def icp(target: OccupiedCells, source: np.ndarray, t0: np.ndarray, iterations: int,
        yaw_only: bool = False) -> tuple[np.ndarray, float]:
    """(refined T, inlier fraction): source points (b frame) pulled onto the target's occupied cell
    centres (a frame)."""
    t = np.asarray(t0, dtype=np.float64).copy()
    coarse = max(1, iterations // 2)
    held = np.full(max(0, iterations - coarse), 1.5)
    radii = np.concatenate([np.geomspace(6.0, 1.5, coarse), held]) * target.resolution
    frac = 0.0
    previous = None
    for k, r in enumerate(radii):
        ok, nearest = target.nearest(apply(t, source), r)
        frac = float(ok.mean()) if len(ok) else 0.0
        if ok.sum() < 10:
            break
        pairs = np.where(ok[:, None], nearest, np.nan)
        if previous is not None and np.array_equal(pairs, previous, equal_nan=True):
            if k >= coarse:  # same pairs under the held radius: every further step repeats this one
                break
            continue  # same pairs, same estimate
        previous = pairs
        t = estimate(source[ok], nearest[ok], yaw_only)
    return t, frac


@nb.njit(**_JIT)
def _shift_scores(field, keys, steps):
    """Sum of the trilinearly interpolated field at keys (fractional cell indices) + each shift."""
    mx, my, mz = field.shape
    n = steps.shape[0]
    out = np.zeros((n, n, n))
    for i in range(n):
        for j in range(n):
            for k in range(n):
                acc = 0.0
                for p in range(keys.shape[0]):
                    x = keys[p, 0] + steps[i]
                    y = keys[p, 1] + steps[j]
                    z = keys[p, 2] + steps[k]
                    x0, y0, z0 = int(np.floor(x)), int(np.floor(y)), int(np.floor(z))
                    if x0 < 0 or y0 < 0 or z0 < 0 or x0 + 1 >= mx or y0 + 1 >= my or z0 + 1 >= mz:
                        continue
                    fx, fy, fz = x - x0, y - y0, z - z0
                    for a in range(2):
                        wa = fx if a else 1.0 - fx
                        for b in range(2):
                            wb = fy if b else 1.0 - fy
                            for c in range(2):
                                wc = fz if c else 1.0 - fz
                                acc += wa * wb * wc * field[x0 + a, y0 + b, z0 + c]
                out[i, j, k] = acc
    return out


def subcell_shift(target_occupied: np.ndarray, target_offset: np.ndarray, resolution: float,
                  source: np.ndarray, t: np.ndarray) -> np.ndarray:
    """t moved by the translation (within +-1 cell, quarter-cell steps) that lays the source points
    (b frame, metres) highest on the target's occupied cells smoothed by a Gaussian of one cell."""
    keys = apply(t, source) / resolution - target_offset
    lo = np.maximum(np.floor(keys.min(axis=0)).astype(np.int64) - 4, 0)
    hi = np.minimum(np.ceil(keys.max(axis=0)).astype(np.int64) + 5, np.array(target_occupied.shape))
    if len(source) == 0 or np.any(hi - lo < 2):
        return t
    crop = target_occupied[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]].astype(np.float32)
    field = gaussian(crop, radius=2, sigma=1.0)
    scores = _shift_scores(field, np.ascontiguousarray(keys - lo), SUBCELL_STEPS)
    best = np.array(np.unravel_index(int(np.argmax(scores)), scores.shape))
    out = t.copy()
    out[:3, 3] += SUBCELL_STEPS[best] * resolution
    return out


FIELD_CELLS = 3
"""Distances in the field fit's distance field are clipped at this many cells: a point farther from
a's surfaces than that is outside the overlap and pulls nothing."""


@nb.njit(**_JIT)
def distance_field(occupied, lo, shape, max_cells):
    """Euclidean distance (cells) from each cell of the box [lo, lo + shape) of `occupied` to the
    nearest occupied cell centre, clipped at max_cells; occupied cells outside the box count too.
    Squared distances are minimised one axis at a time (exact: dx^2 + dy^2 + dz^2 separates), each
    pass over a window of max_cells, so the cost is linear in the box."""
    r = int(np.ceil(max_cells))
    mx, my, mz = occupied.shape
    big = np.float32(max_cells * max_cells + 1.0)
    # the box grown by r on each side (clipped to the grid), where occupied cells can reach it from
    gx0, gy0 = max(0, lo[0] - r), max(0, lo[1] - r)
    gx1, gy1 = min(mx, lo[0] + shape[0] + r), min(my, lo[1] + shape[1] + r)
    z0 = lo[2]
    nx, ny = gx1 - gx0, gy1 - gy0
    d1 = np.full((nx, ny, shape[2]), big)  # along z: only the box's z range is needed after it
    for x in range(nx):
        for y in range(ny):
            for k in range(shape[2]):
                z = z0 + k
                for dz in range(-r, r + 1):
                    zz = z + dz
                    if 0 <= zz < mz and occupied[gx0 + x, gy0 + y, zz]:
                        v = np.float32(dz * dz)
                        if v < d1[x, y, k]:
                            d1[x, y, k] = v
    d2 = np.full((nx, shape[1], shape[2]), big)
    for x in range(nx):
        for j in range(shape[1]):
            y = lo[1] + j - gy0
            for dy in range(-r, r + 1):
                yy = y + dy
                if 0 <= yy < ny:
                    for k in range(shape[2]):
                        v = d1[x, yy, k] + np.float32(dy * dy)
                        if v < d2[x, j, k]:
                            d2[x, j, k] = v
    out = np.full((shape[0], shape[1], shape[2]), big)
    for i in range(shape[0]):
        x = lo[0] + i - gx0
        for dx in range(-r, r + 1):
            xx = x + dx
            if 0 <= xx < nx:
                for j in range(shape[1]):
                    for k in range(shape[2]):
                        v = d2[xx, j, k] + np.float32(dx * dx)
                        if v < out[i, j, k]:
                            out[i, j, k] = v
    for i in range(shape[0]):
        for j in range(shape[1]):
            for k in range(shape[2]):
                out[i, j, k] = min(np.sqrt(out[i, j, k]), np.float32(max_cells))
    return out


@nb.njit(**_JIT)
def _field_normal_equations(field, keys, centre, res, tukey_cells, max_cells):
    """Gauss-Newton normal equations (H 6x6, g 6) and robust cost of the residuals d(q) = field at
    q = keys (fractional cell indices of the moved points), a left twist (rotation about centre,
    translation) as unknowns, Tukey weights of scale tukey_cells; points outside the field or at its
    clip distance are left out. Distances and lever arms in metres."""
    mx, my, mz = field.shape
    h = np.zeros((6, 6))
    g = np.zeros(6)
    j = np.zeros(6)
    cost = 0.0
    used = 0
    c2 = tukey_cells * tukey_cells
    for p in range(keys.shape[0]):
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
                    v = field[x0 + a, y0 + b, z0 + c]
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
        # residual in metres; gradient of the distance (cells per cell = metres per metre)
        r = d * res
        qx = keys[p, 0] * res - centre[0]
        qy = keys[p, 1] * res - centre[1]
        qz = keys[p, 2] * res - centre[2]
        j[0] = qy * gz - qz * gy
        j[1] = qz * gx - qx * gz
        j[2] = qx * gy - qy * gx
        j[3], j[4], j[5] = gx, gy, gz
        for s in range(6):
            g[s] += w * j[s] * r
            for t in range(6):
                h[s, t] += w * j[s] * j[t]
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


def field_fit(target_occupied: np.ndarray, target_offset: np.ndarray, resolution: float, source: np.ndarray,
              t: np.ndarray, iterations: int = 20, tukey_cells: float = 1.5,
              max_step_cells: float = 0.5) -> tuple[np.ndarray, float]:
    """(t refined, robust mean distance in metres of the source points to a's surfaces): 6-DoF
    Levenberg-Marquardt on the distance (trilinear, sub-cell) from the moved source points (b frame,
    metres) to the target's occupied cell centres, Tukey-weighted; points beyond FIELD_CELLS of any
    target cell (outside the overlap) do not count. Each step is held within max_step_cells at the
    points' extent and taken only when it lowers the cost, so the result never scores worse than t."""
    t = np.asarray(t, dtype=np.float64).copy()
    source = np.ascontiguousarray(source, dtype=np.float64)
    if len(source) == 0:
        return t, float("inf")
    offset = np.asarray(target_offset, dtype=np.int64)
    keys = apply(t, source) / resolution - offset
    if not np.all(np.isfinite(keys)):
        return t, float("inf")
    margin = FIELD_CELLS + 2
    lo = np.maximum(np.floor(keys.min(axis=0)).astype(np.int64) - margin, 0)
    hi = np.minimum(np.ceil(keys.max(axis=0)).astype(np.int64) + margin + 1, np.array(target_occupied.shape))
    if np.any(hi - lo < 2):
        return t, float("inf")
    field = distance_field(target_occupied, lo, hi - lo, float(FIELD_CELLS))
    origin = (lo + offset) * resolution  # metres of the field's cell [0, 0, 0]

    def normal_equations(tt):
        k = np.ascontiguousarray(apply(tt, source) / resolution - offset - lo)
        centre = apply(tt, source).mean(axis=0) - origin
        return (*_field_normal_equations(field, k, centre, resolution, tukey_cells, float(FIELD_CELLS)),
                centre + origin)

    h, g, cost, used, centre = normal_equations(t)
    extent = max(float(np.abs(apply(t, source) - centre).max()), resolution)
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
        limit = max_step_cells * resolution
        if reach > limit:
            step *= limit / reach
        trial = _twist(step, centre) @ t
        h2, g2, cost2, used2, centre2 = normal_equations(trial)
        if cost2 < cost:
            t, h, g, cost, used, centre = trial, h2, g2, cost2, used2, centre2
            damping = max(damping / 3.0, 1e-6)
            if reach < 1e-4 * resolution:
                break
        else:
            damping *= 4.0
            if damping > 1e4:
                break
    return t, (np.sqrt(6.0 * cost / max(1, len(source))) * resolution if used else float("inf"))

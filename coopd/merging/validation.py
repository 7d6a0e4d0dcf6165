"""Validation of a candidate transform against both full-resolution grids (thesis §8.8 future work).

Occupied cells on vertical structures of each map are carried into the other. Landing on (or next
to) an occupied cell is an agreement; landing on a free cell with no occupied neighbour is a conflict
(a wall where the other map saw through). Unknown says nothing.
score = agree / (agree + conflicts), counted both ways.
"""

from dataclasses import dataclass

import numba as nb
import numpy as np

from coopd.kernel_cache import CACHE as KERNEL_CACHE

from ..geometry import invert
from ..grid import OccupancyGrid

_JIT = {"nogil": True, "cache": KERNEL_CACHE}
UNSEEN, FREE, NEAR_OCCUPIED = 0, 1, 2


@dataclass(frozen=True)
class MapSummary:
    """What validation and refinement need of a map: cell classes and a sample of occupied points."""

    classes: np.ndarray
    offset: np.ndarray
    resolution: float
    occupied_m: np.ndarray
    """All occupied cell centres (metres, map frame)."""
    sample_m: np.ndarray
    """At most validation_max_points of the occupied cells on vertical structures, spread evenly."""


@nb.njit(**_JIT)
def classify(cells, threshold):
    """UNSEEN / FREE / NEAR_OCCUPIED (occupied within one cell, 26-neighbourhood) per cell."""
    mx, my, mz = cells.shape
    out = np.zeros(cells.shape, dtype=np.uint8)
    for x in range(mx):
        for y in range(my):
            for z in range(mz):
                v = cells[x, y, z]
                if v >= 0:
                    out[x, y, z] = FREE
    for x in range(mx):
        for y in range(my):
            for z in range(mz):
                if cells[x, y, z] >= threshold:
                    for a in range(max(0, x - 1), min(mx, x + 2)):
                        for b in range(max(0, y - 1), min(my, y + 2)):
                            for c in range(max(0, z - 1), min(mz, z + 2)):
                                out[a, b, c] = NEAR_OCCUPIED
    return out


@nb.njit(**_JIT)
def _on_column(cells, threshold, x, y, z, min_run):
    """Whether the occupied cell (x, y, z) is part of a vertical run of at least min_run occupied
    cells (itself included)."""
    run = 1
    k = z - 1
    while run < min_run and k >= 0 and cells[x, y, k] >= threshold:
        run += 1
        k -= 1
    k = z + 1
    while run < min_run and k < cells.shape[2] and cells[x, y, k] >= threshold:
        run += 1
        k += 1
    return run >= min_run


@nb.njit(**_JIT)
def occupied_indices(cells, threshold, min_run):
    """(indices of the occupied cells, indices of those on vertical structure: in a vertical run of at
    least min_run occupied cells, walls and furniture sides), both in array order as np.argwhere gives
    them; one pass to count, one to fill. Floors and ceilings agree under any horizontal shift or
    yaw, so counting them would let a wrong transform that merely lays floor on floor look good:
    validation samples vertical structure only. A floor is often two cells thick (its plane near a
    cell boundary) and a tilted one steps up a cell every few metres, so a run of two is no wall."""
    mx, my, mz = cells.shape
    n = m = 0
    for x in range(mx):
        for y in range(my):
            for z in range(mz):
                if cells[x, y, z] >= threshold:
                    n += 1
                    m += _on_column(cells, threshold, x, y, z, min_run)
    occupied = np.empty((n, 3), dtype=np.int64)
    vertical = np.empty((m, 3), dtype=np.int64)
    n = m = 0
    for x in range(mx):
        for y in range(my):
            for z in range(mz):
                if cells[x, y, z] >= threshold:
                    occupied[n, 0], occupied[n, 1], occupied[n, 2] = x, y, z
                    n += 1
                    if _on_column(cells, threshold, x, y, z, min_run):
                        vertical[m, 0], vertical[m, 1], vertical[m, 2] = x, y, z
                        m += 1
    return occupied, vertical


def summarise(grid: OccupancyGrid, threshold: int, max_points: int, min_run: int) -> MapSummary:
    """Classes and occupied points of a grid, computed once per map; vertical structure is a run of at
    least min_run occupied cells."""
    occupied, vertical = occupied_indices(grid.cells, threshold, min_run)
    pts = (occupied + grid.offset) * grid.resolution
    vert = (vertical + grid.offset) * grid.resolution
    step = max(1, len(vert) // max(1, max_points))
    return MapSummary(classify(grid.cells, threshold), grid.offset, grid.resolution, pts, vert[::step].copy())


@nb.njit(inline="always")
def _landing(p, t, classes, offset, res):
    """The class of the cell of a classified grid that point p moved by t lands in (UNSEEN outside)."""
    x = t[0, 0] * p[0] + t[0, 1] * p[1] + t[0, 2] * p[2] + t[0, 3]
    y = t[1, 0] * p[0] + t[1, 1] * p[1] + t[1, 2] * p[2] + t[1, 3]
    z = t[2, 0] * p[0] + t[2, 1] * p[1] + t[2, 2] * p[2] + t[2, 3]
    kx = int(np.floor(x / res + 0.5)) - offset[0]
    ky = int(np.floor(y / res + 0.5)) - offset[1]
    kz = int(np.floor(z / res + 0.5)) - offset[2]
    mx, my, mz = classes.shape
    if kx < 0 or ky < 0 or kz < 0 or kx >= mx or ky >= my or kz >= mz:
        return UNSEEN
    return classes[kx, ky, kz]


@nb.njit(**_JIT)
def _count(points, t, classes, offset, res):
    """(agreements, conflicts) of points moved by t into a classified grid."""
    agree = 0
    conflict = 0
    for i in range(points.shape[0]):
        c = _landing(points[i], t, classes, offset, res)
        if c == NEAR_OCCUPIED:
            agree += 1
        elif c == FREE:
            conflict += 1
    return agree, conflict


@nb.njit(**_JIT)
def _agreeing(points, t, classes, offset, res):
    """Which points moved by t land next to an occupied cell of a classified grid."""
    out = np.zeros(points.shape[0], dtype=np.bool_)
    for i in range(points.shape[0]):
        out[i] = _landing(points[i], t, classes, offset, res) == NEAR_OCCUPIED
    return out


@dataclass(frozen=True)
class Agreement:
    """How well a transform b -> a makes the two maps agree."""

    agree: int
    conflicts: int

    @property
    def score(self) -> float:
        return self.agree / max(1, self.agree + self.conflicts)

    def support(self, conflict_weight: float) -> float:
        """Ranking value: agreements minus weighted conflicts (MergeParams.conflict_weight)."""
        return self.agree - conflict_weight * self.conflicts


def agreement(a: MapSummary, b: MapSummary, t_ab: np.ndarray) -> Agreement:
    """Agreement of b moved into a by t_ab, counted from both sides."""
    t_ab = np.ascontiguousarray(t_ab, dtype=np.float64)
    g1, c1 = _count(b.sample_m, t_ab, a.classes, a.offset, a.resolution)
    g2, c2 = _count(a.sample_m, invert(t_ab), b.classes, b.offset, b.resolution)
    return Agreement(int(g1 + g2), int(c1 + c2))


def agreeing_points(a: MapSummary, b: MapSummary, t_ab: np.ndarray) -> np.ndarray:
    """b's vertical-structure samples that t_ab lands next to an occupied cell of a, in a's frame."""
    t_ab = np.ascontiguousarray(t_ab, dtype=np.float64)
    near = _agreeing(b.sample_m, t_ab, a.classes, a.offset, a.resolution)
    return b.sample_m[near] @ t_ab[:3, :3].T + t_ab[:3, 3]


def _turn_about(yaw_rad: float, centre: np.ndarray) -> np.ndarray:
    """A turn about the vertical line through centre."""
    c, s = np.cos(yaw_rad), np.sin(yaw_rad)
    t = np.eye(4)
    t[:2, :2] = ((c, -s), (s, c))
    t[:2, 3] = centre[:2] - t[:2, :2] @ centre[:2]
    return t


def loosest_move(a: MapSummary, b: MapSummary, t_ab: np.ndarray, conflict_weight: float, yaw_deg: float,
                 shift_m: float) -> tuple[str, float]:
    """The move of b away from t_ab that keeps the most of its support, and the share it keeps: b
    turned by +-yaw_deg about the middle of where the maps agree (the agreeing samples of both, in a's
    frame), or slid +-shift_m along either horizontal axis of that agreement. An overlap that pins
    the transform loses its support under every such move; one pole keeps it under any turn about
    itself and one straight wall under a slide along it, so the maps do not say where b belongs,
    however well they agree."""
    t_ab = np.ascontiguousarray(t_ab, dtype=np.float64)
    base = agreement(a, b, t_ab).support(conflict_weight)
    from_a = agreeing_points(b, a, invert(t_ab))
    pts = np.concatenate([agreeing_points(a, b, t_ab), from_a @ t_ab[:3, :3].T + t_ab[:3, 3]])
    if base <= 0 or len(pts) < 3:
        return "no agreement to move", 1.0  # nothing pins b
    centre = pts.mean(axis=0)
    _, axes = np.linalg.eigh(np.cov((pts[:, :2] - centre[:2]).T))
    moves = {f"a {yaw_deg:g} deg turn": _turn_about(np.radians(yaw_deg), centre),
             f"a -{yaw_deg:g} deg turn": _turn_about(-np.radians(yaw_deg), centre)}
    for name, axis in (("along", axes[:, 1]), ("across", axes[:, 0])):
        for sign in (1, -1):
            m = np.eye(4)
            m[:2, 3] = sign * shift_m * axis
            moves[f"a {sign * shift_m:g} m slide {name} the overlap"] = m
    kept = {name: agreement(a, b, m @ t_ab).support(conflict_weight) / base for name, m in moves.items()}
    name = max(kept, key=kept.get)
    return name, float(kept[name])

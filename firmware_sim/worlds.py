"""Seeded world generators (six analogues of the thesis environments), their MJCF and ground truth."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from firmware_sim.shapes import Cylinder, Shape, box_from_corners
from firmware_sim.voxelize import voxelize
from firmware_sim.worldgen import generate, is_generated, parse_spec

WALL_RGBA = (0.85, 0.85, 0.8, 1.0)
FURNITURE_RGBA = (0.55, 0.4, 0.3, 1.0)
DOOR_HEIGHT = 2.1
START_SEPARATION_M = 1.0
START_CLEARANCE_M = 0.8
FLIGHT_ALTITUDES_M = (1.0, 1.3, 1.6)


@dataclass
class World:
    """A generated world: its solid primitives, bounds, and a closed exploration loop at floor level."""

    name: str
    seed: int
    shapes: list[Shape]
    bounds_min: np.ndarray
    bounds_max: np.ndarray
    loop: np.ndarray  # (k, 2) vertices of a closed, collision-free exploration loop in the world xy plane
    _gt_cache: dict = field(default_factory=dict, repr=False)

    @property
    def mjcf(self) -> str:
        """Return a standalone MJCF document holding only the world geometry."""
        return compose_mjcf(self, vehicle_bodies="")

    def geoms_mjcf(self) -> str:
        """Return the world's <geom> elements (to be placed in a worldbody)."""
        return "\n    ".join(s.mjcf() for s in self.shapes)

    def ground_truth(self, resolution: float = 0.1) -> tuple[np.ndarray, np.ndarray]:
        """Voxelise the geometry: (occ[x, y, z] bool, world coordinates of the centre of cell [0,0,0])."""
        occ, origin = self._grid(resolution)
        return occ.copy(), origin.copy()

    def _grid(self, resolution: float) -> tuple[np.ndarray, np.ndarray]:
        """The cached ground-truth grid (callers must not modify it)."""
        key = float(resolution)
        if key not in self._gt_cache:
            self._gt_cache[key] = voxelize(self.shapes, self.bounds_min, self.bounds_max, key)
        return self._gt_cache[key]

    def loop_length(self) -> float:
        """Length of the closed exploration loop in metres."""
        d = np.diff(np.vstack([self.loop, self.loop[:1]]), axis=0)
        return float(np.sum(np.hypot(d[:, 0], d[:, 1])))

    def is_clear(self, x: float, y: float, radius: float) -> bool:
        """True if no geometry lies within radius (xy) of (x, y) between 5 cm and 2 m above the floor."""
        occ, origin = self._grid(0.1)
        idx = np.round((np.array([x, y]) - origin[:2]) / 0.1).astype(int)
        r = int(math.ceil(radius / 0.1))
        z0, z1 = int(round((0.05 - origin[2]) / 0.1)), int(round((2.0 - origin[2]) / 0.1))
        return not occ[max(0, idx[0] - r) : idx[0] + r + 1, max(0, idx[1] - r) : idx[1] + r + 1, z0:z1].any()

    def start_poses(self, n: int) -> list[tuple[float, float, float, float]]:
        """Suggest n collision-free start poses (x, y, z, yaw) on the floor, spread along the loop."""
        if n < 1:
            raise ValueError("n must be at least 1")
        total = self.loop_length()
        chosen: list[tuple[float, float, float, float]] = []
        arcs: list[float] = []
        step = 0.25
        for i in range(n):
            s = i * total / n
            for _ in range(int(total / step) + 1):
                (x, y), yaw = point_on_loop(self.loop, s)
                x, y = float(x), float(y)
                far = all(math.hypot(x - c[0], y - c[1]) >= START_SEPARATION_M for c in chosen)
                if far and self.is_clear(x, y, START_CLEARANCE_M):
                    break
                s = (s + step) % total
            else:
                raise ValueError(f"world {self.name} cannot host {n} separated start poses")
            chosen.append((x, y, 0.0, yaw))
            arcs.append(s)
        self._start_arcs = arcs
        return chosen

    def route(self, vehicle_index: int, n_vehicles: int) -> list[np.ndarray]:
        """Built-in exploration route (world-frame waypoints) for vehicle i of n started at start_poses(n)."""
        starts = self.start_poses(n_vehicles)
        s0 = self._start_arcs[vehicle_index]
        alt = FLIGHT_ALTITUDES_M[vehicle_index % len(FLIGHT_ALTITUDES_M)]
        x0, y0, _, _ = starts[vehicle_index]
        pts = loop_from(self.loop, s0)
        return [np.array([x0, y0, alt])] + [np.array([p[0], p[1], alt]) for p in pts]


def point_on_loop(loop: np.ndarray, s: float) -> tuple[np.ndarray, float]:
    """Return the point at arc length s along the closed loop and the heading (rad, ENU) there."""
    pts = np.vstack([loop, loop[:1]])
    seg = np.diff(pts, axis=0)
    lengths = np.hypot(seg[:, 0], seg[:, 1])
    s = s % float(np.sum(lengths))
    for k, length in enumerate(lengths):
        if s <= length and length > 0:
            p = pts[k] + seg[k] * (s / length)
            return p, math.atan2(seg[k, 1], seg[k, 0])
        s -= length
    return pts[0].copy(), math.atan2(seg[0, 1], seg[0, 0])


def loop_from(loop: np.ndarray, s0: float) -> list[np.ndarray]:
    """Return the loop's vertices visited from arc length s0 once around, ending at the point s0 again."""
    pts = np.vstack([loop, loop[:1]])
    seg = np.diff(pts, axis=0)
    cum = np.concatenate([[0.0], np.cumsum(np.hypot(seg[:, 0], seg[:, 1]))])
    total = cum[-1]
    s0 = s0 % total
    start, _ = point_on_loop(loop, s0)
    k = int(np.searchsorted(cum, s0, side="right"))
    order = [loop[(k + j) % len(loop)] for j in range(len(loop))]
    return [p.copy() for p in order] + [start]


def compose_mjcf(world: World, vehicle_bodies: str, timestep: float = 0.004) -> str:
    """Return a complete MJCF document of the world geometry plus the given vehicle <body> elements."""
    return f"""<mujoco model="{world.name}">
  <option timestep="{timestep}" gravity="0 0 -9.81" integrator="implicitfast"/>
  <default><geom friction="0.8 0.005 0.0001" condim="3"/></default>
  <worldbody>
    <light pos="0 0 10" dir="0 0 -1"/>
    {world.geoms_mjcf()}
    {vehicle_bodies}
  </worldbody>
</mujoco>
"""


# ----------------------------------------------------------------------------------------------
# Building blocks


class _Builder:
    """Accumulates shapes with unique names."""

    def __init__(self) -> None:
        self.shapes: list[Shape] = []

    def box(self, kind: str, lo, hi, rgba=FURNITURE_RGBA) -> None:
        """Add a box by its corners."""
        self.shapes.append(box_from_corners(f"{kind}_{len(self.shapes)}", lo, hi, rgba))

    def cylinder(self, kind: str, x: float, y: float, z0: float, z1: float, r: float, rgba=FURNITURE_RGBA):
        """Add a vertical cylinder standing from z0 to z1."""
        self.shapes.append(
            Cylinder(f"{kind}_{len(self.shapes)}", (x, y, (z0 + z1) / 2), r, (z1 - z0) / 2, rgba)
        )

    def floor(self, x1: float, y1: float) -> None:
        """Add a 0.1 m thick floor slab whose top is z = 0 over [0, x1] x [0, y1]."""
        self.box("floor", (0, 0, -0.1), (x1, y1, 0), (0.5, 0.5, 0.5, 1))

    def wall(self, a, b, height: float, thick: float = 0.1, doors=()) -> None:
        """Add an axis-aligned wall from point a to b (2D), cutting door gaps (centre, width) with lintels."""
        (ax, ay), (bx, by) = a, b
        along_x = abs(by - ay) < 1e-9
        lo_s, hi_s = (min(ax, bx), max(ax, bx)) if along_x else (min(ay, by), max(ay, by))
        fixed = ay if along_x else ax
        cuts = sorted((c - w / 2, c + w / 2) for c, w in doors)
        pieces, cursor = [], lo_s
        for c0, c1 in cuts:
            pieces.append((cursor, c0, 0.0, height))
            pieces.append((c0, c1, DOOR_HEIGHT, height))
            cursor = c1
        pieces.append((cursor, hi_s, 0.0, height))
        for s0, s1, z0, z1 in pieces:
            if s1 - s0 < 1e-6 or z1 - z0 < 1e-6:
                continue
            if along_x:
                self.box("wall", (s0, fixed - thick / 2, z0), (s1, fixed + thick / 2, z1), WALL_RGBA)
            else:
                self.box("wall", (fixed - thick / 2, s0, z0), (fixed + thick / 2, s1, z1), WALL_RGBA)

    def outer_walls(self, x1: float, y1: float, height: float, thick: float = 0.1) -> None:
        """Add four walls whose inner faces are the rectangle [0, x1] x [0, y1]."""
        t = thick
        self.box("wall", (-t, -t, 0), (x1 + t, 0, height), WALL_RGBA)
        self.box("wall", (-t, y1, 0), (x1 + t, y1 + t, height), WALL_RGBA)
        self.box("wall", (-t, 0, 0), (0, y1, height), WALL_RGBA)
        self.box("wall", (x1, 0, 0), (x1 + t, y1, height), WALL_RGBA)

    def table(self, x0, y0, x1, y1, height=0.75) -> None:
        """Add a table: a 4 cm top on four legs."""
        self.box("tabletop", (x0, y0, height - 0.04), (x1, y1, height))
        for lx, ly in (
            (x0 + 0.05, y0 + 0.05),
            (x1 - 0.05, y0 + 0.05),
            (x0 + 0.05, y1 - 0.05),
            (x1 - 0.05, y1 - 0.05),
        ):
            self.cylinder("tableleg", lx, ly, 0.0, height - 0.04, 0.03)

    def rack(self, x0, y0, x1, y1, height, levels) -> None:
        """Add an open pallet rack: corner posts and horizontal boards."""
        for px, py in (
            (x0 + 0.05, y0 + 0.05),
            (x1 - 0.05, y0 + 0.05),
            (x0 + 0.05, y1 - 0.05),
            (x1 - 0.05, y1 - 0.05),
        ):
            self.box("rackpost", (px - 0.05, py - 0.05, 0), (px + 0.05, py + 0.05, height))
        for k in range(levels):
            z = 0.15 + k * (height - 0.2) / max(1, levels - 1) if levels > 1 else 0.15
            self.box("rackboard", (x0, y0, z - 0.03), (x1, y1, z + 0.03))


def _bounds(x1: float, y1: float, height: float, margin: float = 0.2):
    """World bounds covering the floor, outer walls and a little margin."""
    return np.array([-margin, -margin, -0.1]), np.array([x1 + margin, y1 + margin, height + 0.1])


def _scale(size) -> float:
    """Interpret the size option: None means 1.0, a number is a scale on the world's default extent."""
    if size is None:
        return 1.0
    s = float(size)
    if not (0.5 <= s <= 4.0):
        raise ValueError(f"size is a scale factor between 0.5 and 4, got {size!r}")
    return s


# ----------------------------------------------------------------------------------------------
# The six worlds


def _maze(seed: int, size) -> World:
    """A perfect maze of 2 m cells (6 x 6 by default), carved by a seeded depth-first search."""
    rng = np.random.default_rng(seed)
    n = max(3, round(6 * _scale(size)))
    cell, height = 2.0, 2.5
    open_edges: set[tuple[tuple[int, int], tuple[int, int]]] = set()
    visited = {(0, 0)}
    stack, tour = [(0, 0)], [(0, 0)]
    while stack:
        cx, cy = stack[-1]
        nbrs = [
            (cx + dx, cy + dy)
            for dx, dy in ((1, 0), (-1, 0), (0, 1), (0, -1))
            if 0 <= cx + dx < n and 0 <= cy + dy < n and (cx + dx, cy + dy) not in visited
        ]
        if nbrs:
            nxt = nbrs[int(rng.integers(len(nbrs)))]
            open_edges.add(tuple(sorted(((cx, cy), nxt))))
            visited.add(nxt)
            stack.append(nxt)
            tour.append(nxt)
        else:
            stack.pop()
            if stack:
                tour.append(stack[-1])
    b = _Builder()
    side = n * cell
    b.floor(side, side)
    b.outer_walls(side, side, height)
    for i in range(n):
        for j in range(n):
            if i + 1 < n and ((i, j), (i + 1, j)) not in open_edges:
                x = (i + 1) * cell
                b.box(
                    "wall",
                    (x - 0.05, j * cell - 0.05, 0),
                    (x + 0.05, (j + 1) * cell + 0.05, height),
                    WALL_RGBA,
                )
            if j + 1 < n and ((i, j), (i, j + 1)) not in open_edges:
                y = (j + 1) * cell
                b.box(
                    "wall",
                    (i * cell - 0.05, y - 0.05, 0),
                    ((i + 1) * cell + 0.05, y + 0.05, height),
                    WALL_RGBA,
                )
    centres = [((i + 0.5) * cell, (j + 0.5) * cell) for i, j in tour[:-1]]
    loop = _simplify(np.array(centres))
    lo, hi = _bounds(side, side, height)
    return World("maze", seed, b.shapes, lo, hi, loop)


def _small_house(seed: int, size) -> World:
    """Four rooms (living, kitchen, bedroom, study) joined by doors of different widths; sofa, tables."""
    rng = np.random.default_rng(seed)
    k = _scale(size)
    X, Y, H = 12.0 * k, 10.0 * k, 2.7
    mx, my = X / 2, Y / 2
    jit = lambda a: float(rng.uniform(-a, a))  # noqa: E731
    d_lk, d_lb, d_ks, d_bs = my / 2 + jit(0.4), mx / 2 + jit(0.4), 1.5 * mx + jit(0.4), 1.5 * my + jit(0.4)
    widths = rng.permutation([1.4, 0.9, 1.0, 0.8])
    b = _Builder()
    b.floor(X, Y)
    b.outer_walls(X, Y, H)
    b.wall((mx, 0), (mx, my), H, doors=[(d_lk, widths[0])])
    b.wall((mx, my), (mx, Y), H, doors=[(d_bs, widths[3])])
    b.wall((0, my), (mx, my), H, doors=[(d_lb, widths[1])])
    b.wall((mx, my), (X, my), H, doors=[(d_ks, widths[2])])
    s = jit(0.3)
    b.box("sofa", (1.0 + s, 0.1, 0), (3.0 + s, 0.95, 0.45))
    b.box("sofaback", (1.0 + s, 0.1, 0.45), (3.0 + s, 0.3, 0.85))
    b.table(0.6, my / 2 - 0.5 + jit(0.2), 1.8, my / 2 + 0.5 + jit(0.2), height=0.45)
    b.box("counter", (mx + 0.5, 0.05, 0), (X - 0.5, 0.65, 0.9))
    b.table(X - 2.0, 1.4 + jit(0.2), X - 0.6, 2.6 + jit(0.2))
    b.box("bed", (0.05, Y - 2.1, 0), (1.65, Y - 0.05, 0.5))
    b.box("wardrobe", (mx - 2.0, Y - 0.65, 0), (mx - 0.6, Y - 0.05, 2.0))
    b.table(X - 1.6, Y - 1.0, X - 0.4, Y - 0.4)
    b.box("bookshelf", (X - 0.4, my + 1.0, 0), (X - 0.05, my + 3.0, 1.8))
    rooms = [(mx / 2, my / 2), (1.5 * mx, my / 2), (1.5 * mx, 1.5 * my), (mx / 2, 1.5 * my)]
    doors = [((mx, d_lk), (1, 0)), ((d_ks, my), (0, 1)), ((mx, d_bs), (-1, 0)), ((d_lb, my), (0, -1))]
    loop = []
    for room, ((dx, dy), (nx, ny)) in zip(rooms, doors, strict=True):
        loop += [room, (dx - 0.7 * nx, dy - 0.7 * ny), (dx + 0.7 * nx, dy + 0.7 * ny)]
    lo, hi = _bounds(X, Y, H)
    return World("small_house", seed, b.shapes, lo, hi, np.array(loop))


def _small_warehouse(seed: int, size) -> World:
    """Rows of shelves of different kinds (open racks, solid shelving, stacked boxes) with aisles."""
    rng = np.random.default_rng(seed)
    k = _scale(size)
    n_rows = max(2, round(3 * k))
    X, Y, H = 4.0 * n_rows + 4.0, 20.0 * k, 3.5
    b = _Builder()
    b.floor(X, Y)
    b.outer_walls(X, Y, H)
    aisles = [1.25]
    y0, y1 = 4.0, Y - 4.0
    for r in range(n_rows):
        x0 = 2.5 + 4.0 * r
        kind = r % 3
        if kind == 0:
            for s in np.arange(y0, y1 - 1e-6, 3.0):
                b.rack(x0, s, x0 + 1.0, min(s + 3.0, y1), 2.4, levels=int(rng.integers(3, 5)))
        elif kind == 1:
            b.box("shelving", (x0, y0, 0), (x0 + 1.0, y1, 2.0 + float(rng.uniform(0, 0.4))))
        else:
            for s in np.arange(y0, y1 - 1e-6, 1.2):
                for level in range(int(rng.integers(1, 4))):
                    b.box("crate", (x0, s + 0.05, 0.8 * level), (x0 + 1.0, s + 1.15, 0.8 * level + 0.78))
        aisles.append(x0 + 1.0 + 1.5)
    for s in np.arange(1.0, X - 1.0, 1.5):
        if rng.random() < 0.6:
            b.box("crate", (s, Y - 0.95, 0), (s + 1.0, Y - 0.05, float(rng.uniform(0.5, 1.6))))
    loop = []
    for i, ax in enumerate(aisles):
        ends = [(ax, 2.0), (ax, Y - 2.0)]
        loop += ends if i % 2 == 0 else ends[::-1]
    if len(aisles) % 2 == 1:
        loop.append((aisles[0], Y - 2.0))
    lo, hi = _bounds(X, Y, H)
    return World("small_warehouse", seed, b.shapes, lo, hi, _simplify(np.array(loop)))


def _bookstore(seed: int, size) -> World:
    """A shop with wall shelves, two free-standing shelf rows, a round table and a counter."""
    rng = np.random.default_rng(seed)
    k = _scale(size)
    X, Y, H = 14.0 * k, 12.0 * k, 2.8
    b = _Builder()
    b.floor(X, Y)
    b.outer_walls(X, Y, H)
    b.box("wallshelf", (0.5, Y - 0.4, 0), (X - 0.5, Y - 0.05, 2.0))
    b.box("wallshelf", (0.05, 3.5, 0), (0.4, Y - 0.6, 2.0))
    b.box("wallshelf", (X - 0.4, 3.0, 0), (X - 0.05, Y - 0.6, 2.0))
    ya, yb = Y * 0.45, Y * 0.7
    for yr in (ya, yb):
        b.box("shelfrow", (2.0, yr - 0.3, 0), (X / 2, yr + 0.3, 1.6 + float(rng.uniform(0, 0.3))))
    tx, ty = X * 0.75, (ya + yb) / 2 - 0.2
    b.cylinder("roundtable", tx, ty, 0.72, 0.76, 0.7)
    b.cylinder("tableleg", tx, ty, 0.0, 0.72, 0.08)
    b.box("counter", (X - 5.0, 0.5, 0), (X - 2.0, 1.1, 1.0))
    ys, yn = 2.5, Y - 1.7
    loop = [
        (1.3, ys),
        (X - 1.7, ys),
        (X - 1.7, yn),
        (1.3, yn),
        (1.3, (ya + yb) / 2),
        (X / 2 + 0.8, (ya + yb) / 2),
        (X / 2 + 0.8, ya - 1.2),
        (1.3, ya - 1.2),
    ]
    lo, hi = _bounds(X, Y, H)
    return World("bookstore", seed, b.shapes, lo, hi, np.array(loop))


def _hospital(seed: int, size) -> World:
    """A long corridor lined on both sides with rooms (beds, cabinets), one door per room."""
    rng = np.random.default_rng(seed)
    k = _scale(size)
    n = max(3, round(8 * k))
    room_w, room_d, corr = 5.0, 9.5, 3.0
    X, Y, H = n * room_w, 2 * room_d + corr, 3.0
    yc0, yc1 = room_d, room_d + corr
    b = _Builder()
    b.floor(X, Y)
    b.outer_walls(X, Y, H, thick=0.15)
    south_doors = [(room_w * (i + 0.5) + float(rng.uniform(-1.0, 1.0)), 1.4) for i in range(n)]
    north_doors = [(room_w * (i + 0.5) + float(rng.uniform(-1.0, 1.0)), 1.4) for i in range(n)]
    b.wall((0, yc0), (X, yc0), H, thick=0.15, doors=south_doors)
    b.wall((0, yc1), (X, yc1), H, thick=0.15, doors=north_doors)
    for i in range(1, n):
        b.wall((i * room_w, 0), (i * room_w, yc0), H, thick=0.15)
        b.wall((i * room_w, yc1), (i * room_w, Y), H, thick=0.15)
    for i in range(n):
        x0 = i * room_w
        bx = x0 + float(rng.uniform(0.6, 2.0))
        b.box("bed", (bx, 0.1, 0), (bx + 0.95, 2.2, 0.6))
        b.box("bed", (bx, Y - 2.2, 0), (bx + 0.95, Y - 0.1, 0.6))
        b.box("cabinet", (x0 + room_w - 0.7, 0.1, 0), (x0 + room_w - 0.1, 0.6, 1.2))
        b.box("cabinet", (x0 + room_w - 0.7, Y - 0.6, 0), (x0 + room_w - 0.1, Y - 0.1, 1.2))
    ym = (yc0 + yc1) / 2
    loop = [(1.5, ym)]
    for dx, _ in south_doors:
        loop += [(dx, ym), (dx, yc0 - 3.5), (dx, ym)]
    loop.append((X - 1.5, ym))
    for dx, _ in reversed(north_doors):
        loop += [(dx, ym), (dx, yc1 + 3.5), (dx, ym)]
    lo, hi = _bounds(X, Y, H)
    return World("hospital", seed, b.shapes, lo, hi, _simplify(np.array(loop)))


def _hull_of_circles(c1, r1: float, c2, r2: float, spacing: float) -> np.ndarray:
    """Points every `spacing` metres along the boundary of the convex hull of two circles (CCW)."""
    ang = np.linspace(0, 2 * np.pi, 720, endpoint=False)
    pts = np.vstack(
        [
            np.c_[c1[0] + r1 * np.cos(ang), c1[1] + r1 * np.sin(ang)],
            np.c_[c2[0] + r2 * np.cos(ang), c2[1] + r2 * np.sin(ang)],
        ]
    )
    hull = _convex_hull(pts)
    return _resample_closed(hull, spacing)


def _racetrack(seed: int, size) -> World:
    """An outdoor loop between tyre barriers: a wide curve at one end, a tight hairpin at the other."""
    rng = np.random.default_rng(seed)
    k = _scale(size)
    r1, r2, half_w = 7.0 * k, 4.0 * k, 1.6
    c1 = np.array([2.0 + r1 + half_w + 1.0, 2.0 + r1 + half_w + 1.0])
    c2 = np.array([c1[0] + 25.0 * k, c1[1] + float(rng.uniform(-1.5, 1.5))])
    X = c2[0] + r2 + half_w + 3.0
    Y = c1[1] + r1 + half_w + 3.0
    H = 3.0
    b = _Builder()
    b.floor(X, Y)
    tyre = 0.3
    for edge in (-1, 1):
        ring = _hull_of_circles(c1, r1 + edge * (half_w + tyre), c2, r2 + edge * (half_w + tyre), 2 * tyre)
        for x, y in ring:
            b.cylinder("tyres", float(x), float(y), 0.0, 0.9, tyre, (0.1, 0.1, 0.1, 1))
    for t in np.sort(rng.uniform(0.15, 0.85, size=4)):
        x, y = c1 + t * (c2 - c1)
        b.cylinder("tree", float(x), float(y), 0.0, 3.0, 0.25, (0.3, 0.5, 0.2, 1))
    b.box("grandstand", (c1[0], 0.3, 0), (c2[0], 1.3, 2.0))
    loop = _hull_of_circles(c1, r1, c2, r2, 2.0)
    lo, hi = _bounds(X, Y, H)
    return World("racetrack", seed, b.shapes, lo, hi, loop)


# ----------------------------------------------------------------------------------------------
# Polyline helpers


def _simplify(pts: np.ndarray) -> np.ndarray:
    """Drop repeated and collinear interior vertices of a closed polyline."""
    out: list[np.ndarray] = []
    for p in pts:
        if out and np.allclose(out[-1], p):
            continue
        out.append(np.asarray(p, float))
    changed = True
    while changed and len(out) > 3:
        changed = False
        for i in range(len(out)):
            a, p, c = out[i - 1], out[i], out[(i + 1) % len(out)]
            u, v = p - a, c - p
            if abs(u[0] * v[1] - u[1] * v[0]) < 1e-9 and np.dot(u, v) > 0:
                out.pop(i)
                changed = True
                break
    return np.array(out)


def _convex_hull(pts: np.ndarray) -> np.ndarray:
    """Andrew's monotone chain convex hull, counter-clockwise."""
    p = sorted(map(tuple, pts))
    cross = lambda o, a, b: (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])  # noqa: E731
    lower: list = []
    for q in p:
        while len(lower) >= 2 and cross(lower[-2], lower[-1], q) <= 0:
            lower.pop()
        lower.append(q)
    upper: list = []
    for q in reversed(p):
        while len(upper) >= 2 and cross(upper[-2], upper[-1], q) <= 0:
            upper.pop()
        upper.append(q)
    return np.array(lower[:-1] + upper[:-1])


def _resample_closed(pts: np.ndarray, spacing: float) -> np.ndarray:
    """Resample a closed polyline at equal arc-length steps close to `spacing`."""
    closed = np.vstack([pts, pts[:1]])
    seg = np.hypot(*np.diff(closed, axis=0).T)
    cum = np.concatenate([[0], np.cumsum(seg)])
    n = max(3, int(round(cum[-1] / spacing)))
    s = np.linspace(0, cum[-1], n, endpoint=False)
    return np.c_[np.interp(s, cum, closed[:, 0]), np.interp(s, cum, closed[:, 1])]


GENERATORS: dict[str, Callable[[int, object], World]] = {
    "maze": _maze,
    "small_house": _small_house,
    "small_warehouse": _small_warehouse,
    "bookstore": _bookstore,
    "hospital": _hospital,
    "racetrack": _racetrack,
}


def build_world(name: str, seed: int = 0, size: float | None = None) -> World:
    """Generate the named world deterministically from the seed; size scales its default extent.

    Besides the six names, 'gen', 'gen:SEED' and 'gen:SEED:key=value,...' build a generated world
    (firmware_sim/worldgen.py; a seed in the name wins over `seed`)."""
    if is_generated(name):
        gen_seed, params = parse_spec(name, int(seed))
        return generate(gen_seed, params, _scale(size))
    if name not in GENERATORS:
        raise ValueError(f"unknown world {name!r}; choose one of {sorted(GENERATORS)} "
                         "or gen:SEED[:key=value,...]")
    return GENERATORS[name](int(seed), size)


def world_name(text: str) -> str:
    """argparse type for a world name: one of the six, or a well-formed generated world's name."""
    import argparse

    if is_generated(text):
        try:
            parse_spec(text)
        except ValueError as e:
            raise argparse.ArgumentTypeError(str(e)) from None
    elif text not in GENERATORS:
        known = ", ".join(sorted(GENERATORS))
        raise argparse.ArgumentTypeError(f"unknown world {text!r}; choose one of {known} "
                                         "or gen:SEED[:key=value,...]")
    return text

"""Generated worlds nobody tuned for: `gen:SEED[:key=value,...]`, built from the six worlds' primitives.

A world is a grid of rectangular blocks (columns and rows of random widths). Indoors, some rows and
columns are narrow corridors, the other blocks are merged into rooms; walls stand between rooms,
with doors forming a spanning tree (plus a few extra doors). Outdoors there are no walls: the blocks
are an open field with buildings, trees, containers and barriers. Furniture (clutter) keeps 0.8 m
clear of the exploration loop, which is a closed tour of the block graph (through block centres and
door centres, like the maze's), so every world is flyable by the built-in routes.

Symmetry 'mirror' (about x = X/2) or 'rot180' (about the centre) generates one half and copies it:
such worlds are ambiguous on purpose (a partial map of one half fits the other), for tests that
want it. Every parameter left out is drawn from the seed; World.name spells all of them out, so
build_world(world.name) rebuilds the same world.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace

import numpy as np

from firmware_sim.shapes import Box, Cylinder, Shape

PREFIX = "gen"
SYMMETRIES = ("none", "mirror", "rot180")
MIN_SIDE_M, MAX_SIDE_M = 8.0, 80.0
CLEARANCE_M = 0.8
"""Clutter keeps this far (xy) from the exploration loop."""
APPROACH_M = 0.7
"""The loop crosses a block boundary perpendicularly from this far on either side."""
WALL_RGBA = (0.85, 0.85, 0.8, 1.0)
FURNITURE_RGBA = (0.55, 0.4, 0.3, 1.0)
OUTDOOR_RGBA = (0.45, 0.45, 0.5, 1.0)
TREE_RGBA = (0.3, 0.5, 0.2, 1.0)
DOOR_HEIGHT = 2.1


@dataclass(frozen=True)
class GenParams:
    """What a generated world looks like; None means drawn from the seed."""

    size: tuple[float, float] | None = None
    """Floor extent x, y in metres ('size=30x20'), 8..80 each; drawn 14-36 x 10-26."""
    rooms: int | None = None
    """Indoor: rooms the non-corridor blocks are merged into (at most one per block)."""
    corridors: int | None = None
    """Indoor: corridor strips (rows or columns 2.2-3 m wide) crossing the building, 0..4."""
    clutter: float | None = None
    """Objects per 10 m^2 of floor, 0..5."""
    outdoor: bool | None = None
    """An open field without walls (drawn: one world in four)."""
    symmetry: str = "none"
    """'none', 'mirror' (about x = X/2) or 'rot180' (about the centre)."""
    height: float | None = None
    """Indoor wall height in metres, 2.3..5."""


def is_generated(name: str) -> bool:
    """True if the world name asks for a generated world ('gen' or 'gen:...')."""
    return name == PREFIX or name.startswith(PREFIX + ":")


def parse_spec(name: str, default_seed: int = 0) -> tuple[int, GenParams]:
    """(seed, parameters) of 'gen', 'gen:SEED' or 'gen:SEED:key=value,...'; ValueError if malformed."""
    parts = name.split(":", 2)
    if parts[0] != PREFIX:
        raise ValueError(f"not a generated world name: {name!r}")
    seed = default_seed
    if len(parts) > 1:
        try:
            seed = int(parts[1])
        except ValueError:
            raise ValueError(f"world {name!r}: the seed {parts[1]!r} is not an integer") from None
    if not 0 <= seed < 2**63:
        raise ValueError(f"world {name!r}: the seed must be a non-negative integer")
    params = GenParams()
    known = {f.name for f in fields(GenParams)}
    for item in filter(None, (parts[2] if len(parts) > 2 else "").split(",")):
        key, eq, value = (s.strip() for s in item.partition("="))
        if not eq or key not in known:
            raise ValueError(f"world {name!r}: {item!r} is not one of {', '.join(sorted(known))} = value")
        params = replace(params, **{key: _parse_value(name, key, value)})
    return seed, params


def _parse_value(name: str, key: str, text: str):
    """One parameter's value, range-checked."""
    try:
        if key == "size":
            x, _, y = text.lower().partition("x")
            value = (float(x), float(y))
            ok = all(MIN_SIDE_M <= v <= MAX_SIDE_M for v in value)
        elif key in ("rooms", "corridors"):
            value = int(text)
            ok = 1 <= value <= 200 if key == "rooms" else 0 <= value <= 4
        elif key == "clutter":
            value = float(text)
            ok = 0.0 <= value <= 5.0
        elif key == "outdoor":
            if text.lower() not in ("0", "1", "true", "false", "yes", "no"):
                raise ValueError
            value, ok = text.lower() in ("1", "true", "yes"), True
        elif key == "height":
            value = float(text)
            ok = 2.3 <= value <= 5.0
        else:
            value, ok = text, text in SYMMETRIES
    except ValueError:
        ok = False
    if not ok:
        raise ValueError(f"world {name!r}: {key}={text!r} is out of range or malformed (see GenParams)")
    return value


def resolve(seed: int, params: GenParams, scale: float = 1.0) -> tuple[GenParams, float]:
    """(parameters with every one but `rooms` filled in, share of blocks that become rooms when `rooms`
    is not given). The given ones are kept, the others drawn from the seed; all are drawn in the same
    order whatever is given, so the world does not depend on which were spelled out."""
    rng = np.random.default_rng([seed, 0])
    size = (round(float(rng.uniform(14, 36)) * 2) / 2, round(float(rng.uniform(10, 26)) * 2) / 2)
    outdoor = bool(rng.random() < 0.25)
    corridors = int(rng.integers(0, 3))
    room_share = float(rng.uniform(0.5, 1.0))
    clutter = float(rng.uniform(0.3, 1.5))
    height = float(rng.uniform(2.5, 3.2))
    size = tuple(round(min(MAX_SIDE_M, max(MIN_SIDE_M, v * scale)), 2) for v in params.size or size)
    return GenParams(
        size=size,
        rooms=params.rooms,
        corridors=params.corridors if params.corridors is not None else corridors,
        clutter=round(params.clutter if params.clutter is not None else clutter, 3),
        outdoor=params.outdoor if params.outdoor is not None else outdoor,
        symmetry=params.symmetry,
        height=round(params.height if params.height is not None else height, 2),
    ), room_share


def spec_name(seed: int, p: GenParams) -> str:
    """The world's full name: every parameter spelled out."""
    return (f"{PREFIX}:{seed}:size={p.size[0]:g}x{p.size[1]:g},rooms={p.rooms},corridors={p.corridors},"
            f"clutter={p.clutter:g},outdoor={int(p.outdoor)},symmetry={p.symmetry},height={p.height:g}")


# ----------------------------------------------------------------------------------------------
# Layout: strips, blocks, regions, doors


@dataclass
class _Layout:
    """One (half) world's blocks: column and row edges, region of each block, doors, the loop."""

    xs: np.ndarray
    ys: np.ndarray
    region: dict
    doors: dict
    """Block edge ((i, j), (k, l)) -> (centre along the edge, width) of its door."""
    rooms: int
    """The room count aimed at (reached unless the blocks are too few)."""


def _strips(rng, total: float, corridors: int, corridor_w: float, target: float) -> tuple[list, list]:
    """Edges of strips covering [0, total]: `corridors` narrow ones inserted among room-sized ones
    (each room strip at least 2/3 of max(target, 4.5) m wide); returns (edges, corridor indices)."""
    while corridors and total - corridors * corridor_w < 4.5:
        corridors -= 1
    rest = total - corridors * corridor_w
    n_rooms = max(1, int(rest // max(target, 4.5)))
    widths = list(rest * (w := rng.uniform(0.8, 1.2, n_rooms)) / w.sum())
    corridor_at = []
    for _ in range(corridors):
        k = int(rng.integers(0, len(widths) + 1))
        widths.insert(k, corridor_w)
        corridor_at = [c + (c >= k) for c in corridor_at] + [k]
    return list(np.concatenate([[0.0], np.cumsum(widths)])), sorted(corridor_at)


def _find(parent: dict, a):
    """Union-find root with path halving."""
    while parent[a] != a:
        parent[a] = parent[parent[a]]
        a = parent[a]
    return a


def _layout(rng, width: float, depth: float, p: GenParams, rooms: int | None, share: float) -> _Layout:
    """Blocks, rooms and doors of a world (or half world) over [0, width] x [0, depth]."""
    target = float(rng.uniform(4.5, 6.5))
    corridor_w = float(rng.uniform(2.2, 3.0))
    along_x = int(rng.binomial(p.corridors, 0.5)) if not p.outdoor else 0
    along_y = (p.corridors - along_x) if not p.outdoor else 0
    xs, col_corr = _strips(rng, width, along_y, corridor_w, target)
    ys, row_corr = _strips(rng, depth, along_x, corridor_w, target)
    nx, ny = len(xs) - 1, len(ys) - 1
    blocks = [(i, j) for i in range(nx) for j in range(ny)]
    parent = {b: b for b in blocks}
    corridor = {b for b in blocks if b[0] in col_corr or b[1] in row_corr}
    edges = [((i, j), (i + 1, j)) for i in range(nx - 1) for j in range(ny)]
    edges += [((i, j), (i, j + 1)) for i in range(nx) for j in range(ny - 1)]
    for a, b in edges:
        in_one_corridor = a[0] == b[0] in col_corr or a[1] == b[1] in row_corr
        if p.outdoor or (a in corridor and b in corridor and in_one_corridor):
            parent[_find(parent, a)] = _find(parent, b)
    room_blocks = [b for b in blocks if b not in corridor]
    target_rooms = max(1, round(len(room_blocks) * share)) if rooms is None else rooms
    count = len({_find(parent, b) for b in room_blocks})
    mergeable = [e for e in edges if e[0] not in corridor and e[1] not in corridor]
    for k in rng.permutation(len(mergeable)):
        if count <= target_rooms:
            break
        ra, rb = _find(parent, mergeable[k][0]), _find(parent, mergeable[k][1])
        if ra != rb:
            parent[ra] = rb
            count -= 1
    region = {b: _find(parent, b) for b in blocks}
    doors = {}
    tree = {r: r for r in set(region.values())}
    for k in rng.permutation(len(edges)):
        a, b = edges[k]
        ra, rb = region[a], region[b]
        if ra == rb:
            continue
        joins = _find(tree, ra) != _find(tree, rb)
        if joins:
            tree[_find(tree, ra)] = _find(tree, rb)
        if joins or rng.random() < 0.2:
            doors[(a, b)] = _door(rng, xs, ys, a, b)
    return _Layout(np.array(xs), np.array(ys), region, doors, target_rooms)


def _door(rng, xs, ys, a, b) -> tuple[float, float]:
    """(centre along the shared edge, width) of a door between adjacent blocks a and b."""
    lo, hi = (ys[a[1]], ys[a[1] + 1]) if a[0] != b[0] else (xs[a[0]], xs[a[0] + 1])
    w = float(rng.uniform(1.0, min(1.6, hi - lo - 0.8)))
    return float(rng.uniform(lo + 0.4 + w / 2, hi - 0.4 - w / 2)), w


def _centre(lay: _Layout, b) -> np.ndarray:
    """Centre of block b."""
    i, j = b
    return np.array([(lay.xs[i] + lay.xs[i + 1]) / 2, (lay.ys[j] + lay.ys[j + 1]) / 2])


def _crossing(lay: _Layout, a, b) -> tuple[np.ndarray, np.ndarray]:
    """Where the loop crosses from block a into adjacent block b: (point in a, point in b),
    APPROACH_M either side of the door centre (or of the shared edge's middle if the blocks share a room)."""
    key = (a, b) if (a, b) in lay.doors else (b, a)
    step = np.array([b[0] - a[0], b[1] - a[1]], dtype=float)
    if step[0]:
        x = lay.xs[max(a[0], b[0])]
        y = lay.doors[key][0] if key in lay.doors else (lay.ys[a[1]] + lay.ys[a[1] + 1]) / 2
    else:
        y = lay.ys[max(a[1], b[1])]
        x = lay.doors[key][0] if key in lay.doors else (lay.xs[a[0]] + lay.xs[a[0] + 1]) / 2
    at = np.array([x, y])
    return at - APPROACH_M * step, at + APPROACH_M * step


def _tour(lay: _Layout, rng, root) -> list[np.ndarray]:
    """Closed depth-first tour of the blocks through open edges and doors, from the root's centre
    back to it (the last point repeats the first)."""
    def passable(a, b):
        return lay.region[a] == lay.region[b] or (a, b) in lay.doors or (b, a) in lay.doors

    nx, ny = len(lay.xs) - 1, len(lay.ys) - 1
    seen, stack, pts = {root}, [root], [_centre(lay, root)]
    while stack:
        a = stack[-1]
        nbrs = [(a[0] + dx, a[1] + dy) for dx, dy in ((1, 0), (-1, 0), (0, 1), (0, -1))]
        nbrs = [b for b in nbrs if 0 <= b[0] < nx and 0 <= b[1] < ny and b not in seen and passable(a, b)]
        if nbrs:
            b = nbrs[int(rng.integers(len(nbrs)))]
            seen.add(b)
            stack.append(b)
        else:
            stack.pop()
            if not stack:
                break
            b, a = stack[-1], a
        pts += [*_crossing(lay, a, b), _centre(lay, b)]
    if len(pts) == 1:  # a single block: a rectangle 1 m inside its walls
        (x0, x1), (y0, y1) = lay.xs[root[0]:root[0] + 2] + [1, -1], lay.ys[root[1]:root[1] + 2] + [1, -1]
        pts = [np.array(q) for q in ((x0, y0), (x1, y0), (x1, y1), (x0, y1), (x0, y0))]
    return pts


# ----------------------------------------------------------------------------------------------
# Shapes


class _Shapes:
    """Shapes of a (half) world with unique names."""

    def __init__(self, tag: str) -> None:
        self.tag = tag
        self.items: list[Shape] = []

    def box(self, kind, lo, hi, rgba) -> None:
        """Add a box by its corners."""
        lo, hi = np.asarray(lo, float), np.asarray(hi, float)
        self.items.append(Box(f"{kind}_{self.tag}{len(self.items)}", tuple(map(float, (lo + hi) / 2)),
                              tuple(map(float, (hi - lo) / 2)), rgba))

    def cylinder(self, kind, x, y, z0, z1, r, rgba) -> None:
        """Add a vertical cylinder standing from z0 to z1."""
        self.items.append(Cylinder(f"{kind}_{self.tag}{len(self.items)}", (float(x), float(y), (z0 + z1) / 2),
                                   float(r), (z1 - z0) / 2, rgba))

    def wall(self, a, b, height: float, doors=(), thick: float = 0.1) -> None:
        """An axis-aligned wall from a to b (2D) with door gaps (centre, width) under lintels."""
        along_x = abs(b[1] - a[1]) < 1e-9
        s0, s1 = sorted((a[0], b[0]) if along_x else (a[1], b[1]))
        fixed = a[1] if along_x else a[0]
        pieces, cursor = [], s0
        for c, w in sorted(doors):
            pieces += [(cursor, c - w / 2, 0.0, height), (c - w / 2, c + w / 2, DOOR_HEIGHT, height)]
            cursor = c + w / 2
        pieces.append((cursor, s1, 0.0, height))
        for p0, p1, z0, z1 in pieces:
            if p1 - p0 > 1e-6 and z1 - z0 > 1e-6:
                lo = (p0, fixed - thick / 2, z0) if along_x else (fixed - thick / 2, p0, z0)
                hi = (p1, fixed + thick / 2, z1) if along_x else (fixed + thick / 2, p1, z1)
                self.box("wall", lo, hi, WALL_RGBA)


def _walls(out: _Shapes, lay: _Layout, height: float) -> None:
    """Walls between blocks of different regions, with their doors."""
    for a in lay.region:
        for b in ((a[0] + 1, a[1]), (a[0], a[1] + 1)):
            if b not in lay.region or lay.region[a] == lay.region[b]:
                continue
            door = [lay.doors[(a, b)]] if (a, b) in lay.doors else []
            if b[0] != a[0]:
                x = lay.xs[b[0]]
                out.wall((x, lay.ys[a[1]]), (x, lay.ys[a[1] + 1]), height, door)
            else:
                y = lay.ys[b[1]]
                out.wall((lay.xs[a[0]], y), (lay.xs[a[0] + 1], y), height, door)


def _dense(pts: list[np.ndarray], step: float = 0.1) -> np.ndarray:
    """Points every `step` metres along a polyline."""
    out = [pts[0]]
    for a, b in zip(pts[:-1], pts[1:], strict=True):
        n = max(1, int(math.ceil(np.linalg.norm(b - a) / step)))
        out += [a + (b - a) * k / n for k in range(1, n + 1)]
    return np.array(out)


def _clutter(out: _Shapes, lay: _Layout, rng, p: GenParams, keep_clear: np.ndarray) -> None:
    """Objects in every block, inside it by 0.1 m, CLEARANCE_M from the loop and apart from each other."""
    placed: list[tuple] = []
    for b in sorted(lay.region):
        x0, x1 = lay.xs[b[0]] + 0.1, lay.xs[b[0] + 1] - 0.1
        y0, y1 = lay.ys[b[1]] + 0.1, lay.ys[b[1] + 1] - 0.1
        for _ in range(int(rng.poisson(p.clutter * (x1 - x0) * (y1 - y0) / 10.0))):
            kind, (sx, sy), draw = _object(rng, p)
            for _ in range(30):
                if x1 - x0 <= sx or y1 - y0 <= sy:
                    break
                cx, cy = rng.uniform(x0 + sx / 2, x1 - sx / 2), rng.uniform(y0 + sy / 2, y1 - sy / 2)
                rect = (cx - sx / 2, cy - sy / 2, cx + sx / 2, cy + sy / 2)
                if _rect_distance(rect, keep_clear) >= CLEARANCE_M and all(
                        _rects_apart(rect, q, 0.2) for q in placed):
                    placed.append(rect)
                    draw(out, kind, rect)
                    break


def _object(rng, p: GenParams):
    """(kind, footprint (sx, sy), draw(out, kind, rect)) of one random object."""
    turn = rng.random() < 0.5

    def sized(a, b):
        return (b, a) if turn else (a, b)

    def box_up_to(top, rgba):
        return lambda out, kind, r: out.box(kind, (r[0], r[1], 0.0), (r[2], r[3], top), rgba)

    def cylinder(top, rgba):
        return lambda out, kind, r: out.cylinder(kind, (r[0] + r[2]) / 2, (r[1] + r[3]) / 2, 0.0, top,
                                                 (r[2] - r[0]) / 2, rgba)

    u = rng.random()
    if p.outdoor:
        if u < 0.25:
            return "building", sized(rng.uniform(2, 6), rng.uniform(2, 6)), box_up_to(rng.uniform(2.5, 6),
                                                                                       OUTDOOR_RGBA)
        if u < 0.6:
            d = 2 * rng.uniform(0.15, 0.35)
            return "tree", (d, d), cylinder(rng.uniform(3, 6), TREE_RGBA)
        if u < 0.75:
            return "container", sized(2.4, 6.0), box_up_to(2.6, OUTDOOR_RGBA)
        if u < 0.9:
            return "barrier", sized(0.4, rng.uniform(1.5, 3)), box_up_to(0.9, OUTDOOR_RGBA)
        return "pole", (0.2, 0.2), cylinder(rng.uniform(2, 5), OUTDOOR_RGBA)
    if u < 0.35:
        footprint = sized(rng.uniform(0.3, 0.6), rng.uniform(0.6, 2.0))
        return "cabinet", footprint, box_up_to(rng.uniform(0.8, 2.2), FURNITURE_RGBA)
    if u < 0.6:
        top = float(rng.uniform(0.45, 0.8))

        def table(out, kind, r):
            out.box("tabletop", (r[0], r[1], top - 0.04), (r[2], r[3], top), FURNITURE_RGBA)
            for lx, ly in ((r[0] + 0.05, r[1] + 0.05), (r[2] - 0.05, r[1] + 0.05), (r[0] + 0.05, r[3] - 0.05),
                           (r[2] - 0.05, r[3] - 0.05)):
                out.cylinder("tableleg", lx, ly, 0.0, top - 0.04, 0.03, FURNITURE_RGBA)
        return "table", sized(rng.uniform(0.8, 1.6), rng.uniform(0.6, 1.0)), table
    if u < 0.85:
        return "crate", sized(rng.uniform(0.4, 1.2), rng.uniform(0.4, 1.2)), box_up_to(rng.uniform(0.4, 1.2),
                                                                                       FURNITURE_RGBA)
    d = 2 * rng.uniform(0.15, 0.3)
    return "pillar", (d, d), cylinder(p.height, WALL_RGBA)


def _rect_distance(rect, points: np.ndarray) -> float:
    """Smallest xy distance from the rectangle (x0, y0, x1, y1) to any of the points."""
    if len(points) == 0:
        return math.inf
    dx = np.maximum.reduce([rect[0] - points[:, 0], np.zeros(len(points)), points[:, 0] - rect[2]])
    dy = np.maximum.reduce([rect[1] - points[:, 1], np.zeros(len(points)), points[:, 1] - rect[3]])
    return float(np.min(np.hypot(dx, dy)))


def _rects_apart(a, b, gap: float) -> bool:
    """True if rectangles a and b are at least `gap` apart along x or y."""
    return a[2] + gap <= b[0] or b[2] + gap <= a[0] or a[3] + gap <= b[1] or b[3] + gap <= a[1]


def _image(shape: Shape, f, tag: str) -> Shape:
    """The shape carried by the xy map f (a mirror or a half turn keeps boxes axis-aligned)."""
    x, y = f(np.array(shape.center[:2]))
    centre = (float(x), float(y), shape.center[2])
    return replace(shape, name=shape.name.replace("_", f"_{tag}", 1), center=centre)


# ----------------------------------------------------------------------------------------------


def generate(seed: int, params: GenParams, scale: float = 1.0):
    """Build the generated world (a firmware_sim.worlds.World) for the seed and parameters."""
    from firmware_sim.worlds import World, _simplify

    p, share = resolve(seed, params, scale)
    rng = np.random.default_rng([seed, 1])
    X, Y = p.size
    half = p.symmetry != "none"
    width = X / 2 if half else X
    lay = _layout(rng, width, Y, p, None if p.rooms is None else max(1, round(p.rooms / (1 + half))), share)
    if p.rooms is None:
        p = replace(p, rooms=lay.rooms * (1 + half))
    ny = len(lay.ys) - 1
    out = _Shapes("")
    if not p.outdoor:
        _walls(out, lay, p.height)
    if not half:
        root = sorted(lay.region)[int(rng.integers(len(lay.region)))]
        loop = _tour(lay, rng, root)
        keep_clear = _dense(loop)
    else:
        def f(q):
            return np.array([X - q[0], q[1] if p.symmetry == "mirror" else Y - q[1]])

        left, y_mid, w_mid = _middle_door(rng, lay, p, Y)
        right = (left[0], left[1] if p.symmetry == "mirror" else _row_of(lay, Y - y_mid))
        tour_l, tour_r = _tour(lay, rng, left), _tour(lay, rng, right)
        a_in, b_in = np.array([width - APPROACH_M, y_mid]), np.array([width + APPROACH_M, y_mid])
        loop = tour_l + [a_in, b_in] + [f(q) for q in tour_r] + [b_in, a_in]
        # clutter is placed in the left half: keep clear of both tours and both ends of the crossing
        keep_clear = np.vstack([_dense(tour_l), _dense(tour_r), _dense([_centre(lay, left), a_in]),
                                _dense([_centre(lay, right), f(b_in)])])
    _clutter(out, lay, rng, p, keep_clear)
    shapes = list(out.items)
    if half:
        shapes += [_image(s, f, "m") for s in out.items]
    final = _Shapes("o")
    final.box("floor", (0, 0, -0.1), (X, Y, 0), (0.5, 0.5, 0.5, 1))
    if not p.outdoor:
        t = 0.1
        final.box("wall", (-t, -t, 0), (X + t, 0, p.height), WALL_RGBA)
        final.box("wall", (-t, Y, 0), (X + t, Y + t, p.height), WALL_RGBA)
        final.box("wall", (-t, 0, 0), (0, Y, p.height), WALL_RGBA)
        final.box("wall", (X, 0, 0), (X + t, Y, p.height), WALL_RGBA)
        if half:
            doors = [(y_mid, w_mid)] + ([(Y - y_mid, w_mid)] if p.symmetry == "rot180" and
                                        abs(2 * y_mid - Y) > 1e-9 else [])
            for j in range(ny):
                inside = [d for d in doors if lay.ys[j] < d[0] < lay.ys[j + 1]]
                final.wall((width, lay.ys[j]), (width, lay.ys[j + 1]), p.height, inside)
    top = max(float(s.bounds()[1][2]) for s in shapes + final.items)
    lo, hi = np.array([-0.2, -0.2, -0.1]), np.array([X + 0.2, Y + 0.2, top + 0.1])
    return World(spec_name(seed, p), seed, final.items + shapes, lo, hi,
                  _simplify(np.array(loop[:-1] if np.allclose(loop[0], loop[-1]) else loop)))


def _row_of(lay: _Layout, y: float) -> int:
    """Index of the row containing y."""
    return int(np.clip(np.searchsorted(lay.ys, y) - 1, 0, len(lay.ys) - 2))


def _middle_door(rng, lay: _Layout, p: GenParams, depth: float) -> tuple[tuple[int, int], float, float]:
    """A door in the wall on the symmetry line: (left block beside it, its y, its width). Under a half
    turn the door at y also stands at depth - y, so both places keep 0.4 m from the rows' ends
    (or the door sits in the middle)."""
    i = len(lay.xs) - 2
    for _ in range(200):
        j = int(rng.integers(len(lay.ys) - 1))
        lo, hi = lay.ys[j], lay.ys[j + 1]
        w = float(rng.uniform(1.0, min(1.6, hi - lo - 0.8)))
        y = float(rng.uniform(lo + 0.4 + w / 2, hi - 0.4 - w / 2))
        if p.symmetry == "mirror":
            return (i, j), y, w
        if abs(2 * y - depth) < w + 0.5:
            y = depth / 2
            if not lo + 0.4 + w / 2 <= y <= hi - 0.4 - w / 2:
                continue
        k = _row_of(lay, depth - y)
        if lay.ys[k] + 0.4 + w / 2 <= depth - y <= lay.ys[k + 1] - 0.4 - w / 2:
            return (i, j), y, w
    raise ValueError("no place for a door on the symmetry line")

"""Deterministic building-like occupancy maps for codec tests and the codec benchmark.

A map is mostly unknown: a building of rooms (walls, floor, ceiling slabs) of which a random
walk of rooms has been explored. Explored rooms hold free space with HIMM-like values (mostly
0, some 10..40, rare false hits), occupied walls/floor/ceiling/furniture (60..100, mostly
100), doors between visited rooms, and blind spots the camera never saw (unknown boxes).
"""

import numpy as np

FREE_VALUES = np.array([0, 10, 20, 30, 40, 60], dtype=np.int8)
FREE_WEIGHTS = np.array([0.86, 0.02, 0.08, 0.02, 0.01, 0.01])
HIT_VALUES = np.array([60, 70, 80, 90, 100], dtype=np.int8)
HIT_WEIGHTS = np.array([0.04, 0.06, 0.08, 0.12, 0.70])

THESIS_SIZES = {
    "3.6M": (190, 190, 100),
    "25M": (500, 500, 100),
    "110M": (1050, 1050, 100),
}
"""Grid shapes with the thesis' map sizes (§10.1: 3.61 M, 25 M and 110.25 M cells)."""


def _walls(rng, lo: int, hi: int, min_room: int, max_room: int) -> list[int]:
    """Wall positions between lo and hi, rooms min_room..max_room cells wide."""
    walls = [lo]
    while walls[-1] + min_room < hi:
        walls.append(min(hi, walls[-1] + int(rng.integers(min_room, max_room + 1))))
    if walls[-1] != hi:
        walls[-1] = hi
    return walls


def _fill(rng, box: np.ndarray, values: np.ndarray, weights: np.ndarray) -> None:
    box[...] = rng.choice(values, size=box.shape, p=weights)


def building_map(shape, explored: float = 0.1, seed: int = 0) -> np.ndarray:
    """An int8 (m_x, m_y, m_z) map with about `explored` of its cells known."""
    mx, my, mz = (int(s) for s in shape)
    rng = np.random.default_rng(seed)
    cells = np.full((mx, my, mz), -1, dtype=np.int8)
    floor, ceiling = 2, max(4, mz - 3)
    xs = _walls(rng, mx // 10, mx - mx // 10, 30, 80)
    ys = _walls(rng, my // 10, my - my // 10, 30, 80)
    nrx, nry = len(xs) - 1, len(ys) - 1
    if nrx < 1 or nry < 1:
        xs, ys, nrx, nry = [1, mx - 2], [1, my - 2], 1, 1
    target = explored * cells.size
    known = 0
    visited = set()
    room = (int(rng.integers(nrx)), int(rng.integers(nry)))
    previous = None
    for _ in range(20 * nrx * nry):
        if known >= target:
            break
        if room not in visited:
            visited.add(room)
            known += _explore_room(rng, cells, xs, ys, room, floor, ceiling)
            if previous is not None:
                _door(cells, xs, ys, previous, room, floor, ceiling)
        previous = room
        step = [(1, 0), (-1, 0), (0, 1), (0, -1)][int(rng.integers(4))]
        nxt = (room[0] + step[0], room[1] + step[1])
        if 0 <= nxt[0] < nrx and 0 <= nxt[1] < nry:
            room = nxt
        else:
            previous = None
    return cells


def _explore_room(rng, cells, xs, ys, room, floor, ceiling) -> int:
    """Mark one room as seen: walls and slabs hit, inside free, blind spots left unknown."""
    x0, x1 = xs[room[0]], xs[room[0] + 1]
    y0, y1 = ys[room[1]], ys[room[1] + 1]
    shell = cells[x0:x1 + 1, y0:y1 + 1, floor:ceiling + 1]
    _fill(rng, shell, HIT_VALUES, HIT_WEIGHTS)
    inside = cells[x0 + 1:x1, y0 + 1:y1, floor + 1:ceiling]
    _fill(rng, inside, FREE_VALUES, FREE_WEIGHTS)
    sx, sy, sz = inside.shape
    for _ in range(int(rng.integers(1, 4))):  # furniture
        a = rng.integers(0, [sx, sy, 1])
        b = a + rng.integers([3, 3, 5], [max(4, sx // 3), max(4, sy // 3), max(6, sz // 3)])
        _fill(rng, inside[a[0]:b[0], a[1]:b[1], a[2]:b[2]], HIT_VALUES, HIT_WEIGHTS)
    for _ in range(int(rng.integers(1, 4))):  # blind spots: behind furniture, under the ceiling
        a = rng.integers(0, [sx, sy, sz])
        b = a + rng.integers([4, 4, 4], [max(5, sx // 2), max(5, sy // 2), max(5, sz // 2)])
        inside[a[0]:b[0], a[1]:b[1], a[2]:b[2]] = -1
    return shell.size


def _door(cells, xs, ys, a, b, floor, ceiling) -> None:
    """A free opening in the wall between two neighbouring rooms."""
    height = slice(floor + 1, min(ceiling, floor + 1 + 20))
    if a[0] != b[0]:
        wx = xs[max(a[0], b[0])]
        yc = (ys[a[1]] + ys[a[1] + 1]) // 2
        cells[wx, yc - 4:yc + 4, height] = 0
    else:
        wy = ys[max(a[1], b[1])]
        xc = (xs[a[0]] + xs[a[0] + 1]) // 2
        cells[xc - 4:xc + 4, wy, height] = 0

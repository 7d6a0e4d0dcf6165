"""Deterministic merge-benchmark pairs: a building-like voxel world and ray-cast partial maps of it.

Each partial map is what a drone would build: from viewpoints inside an explored sub-box of the
world, rays go out in every direction; the cells they cross become free, the surface cell they hit
becomes occupied, everything behind stays unknown. Rays are cast in the map's *own* frame: the
drone's start pose near the centre of its box, with a random yaw and roll/pitch <= 3 degrees, so two
maps differ by any yaw and a translation of up to about 10 m (the distance between the boxes); no
resampling artefacts are added and the ground-truth transform between two maps is exact.
"""

from dataclasses import dataclass

import numba as nb
import numpy as np

from coopd.geometry import apply, euler_to_matrix, invert, rigid
from coopd.grid import OccupancyGrid
from coopd.grid.cells import CELL_DTYPE, UNKNOWN
from coopd.kernel_cache import CACHE as KERNEL_CACHE

_JIT = {"nogil": True, "cache": KERNEL_CACHE}


@dataclass(frozen=True)
class World:
    """Boolean solid voxels of a building; array element [0,0,0] is the world origin's cell."""

    solid: np.ndarray
    resolution: float


@dataclass(frozen=True)
class PartialMap:
    """One drone's occupancy grid in its own frame, with the frame's pose in the world."""

    grid: OccupancyGrid
    world_from_map: np.ndarray
    box_m: tuple


@dataclass(frozen=True)
class MergePair:
    """Two partial maps of one world, the true transform b -> a, and their measured overlap."""

    a: OccupancyGrid
    b: OccupancyGrid
    a_from_b: np.ndarray
    overlap: float
    seed: int


def make_world(seed: int = 0, size_m=(25.0, 25.0, 3.0), resolution: float = 0.1) -> World:
    """Rooms with irregular walls and doors, furniture, pillars, floor and ceiling."""
    rng = np.random.default_rng(seed)
    n = np.round(np.asarray(size_m) / resolution).astype(int)
    s = np.zeros(tuple(n), dtype=bool)
    s[:, :, 0] = True
    s[:, :, -1] = True
    s[:2], s[-2:], s[:, :2], s[:, -2:] = True, True, True, True
    door_h = int(2.1 / resolution)
    cuts = []
    for axis in (0, 1):
        pos, walls = 0, []
        while True:
            pos += int(rng.uniform(3.5, 7.0) / resolution)
            if pos > n[axis] - int(3.0 / resolution):
                break
            walls.append(pos)
        cuts.append([0] + walls + [n[axis] - 1])
        for w in walls:
            sl = [slice(None)] * 3
            sl[axis] = slice(w, w + 2)
            s[tuple(sl)] = True
    for axis in (0, 1):
        other = 1 - axis
        for w in cuts[axis][1:-1]:
            edges = cuts[other]
            for lo, hi in zip(edges[:-1], edges[1:], strict=True):
                if hi - lo < int(2.0 / resolution):
                    continue
                width = int(rng.uniform(0.9, 1.6) / resolution)
                start = int(rng.integers(lo + 4, max(lo + 5, hi - width - 4)))
                sl = [slice(None)] * 3
                sl[axis] = slice(w, w + 2)
                sl[other] = slice(start, start + width)
                top = door_h if rng.random() < 0.8 else n[2] - 1
                sl[2] = slice(1, top)
                s[tuple(sl)] = False
    for _ in range(int(size_m[0] * size_m[1] / 6)):
        sx, sy = (rng.uniform(0.3, 1.6, 2) / resolution).astype(int) + 1
        sz = int(rng.uniform(0.3, 2.0) / resolution)
        x0 = int(rng.integers(3, n[0] - sx - 3))
        y0 = int(rng.integers(3, n[1] - sy - 3))
        s[x0:x0 + sx, y0:y0 + sy, 1:1 + sz] = True
    for _ in range(int(size_m[0] * size_m[1] / 60)):
        x0, y0 = int(rng.integers(3, n[0] - 6)), int(rng.integers(3, n[1] - 6))
        s[x0:x0 + 3, y0:y0 + 3, :] = True
    return World(s, resolution)


def fibonacci_directions(count: int) -> np.ndarray:
    """Unit vectors spread evenly over the sphere."""
    i = np.arange(count) + 0.5
    phi = np.arccos(1 - 2 * i / count)
    theta = np.pi * (1 + 5 ** 0.5) * i
    return np.stack([np.cos(theta) * np.sin(phi), np.sin(theta) * np.sin(phi), np.cos(phi)], axis=1)


@nb.njit(**_JIT)
def _cast(solid, wres, origins_m, dirs, rot, trans, max_range, hits, misses, offset, res):
    """Ray-cast in the map frame; world lookups through p_w = rot p_m + trans; count hits/misses."""
    step = 0.5 * res
    nsteps = int(max_range / step)
    wx, wy, wz = solid.shape
    mx, my, mz = hits.shape
    for v in range(origins_m.shape[0]):
        ox, oy, oz = origins_m[v, 0], origins_m[v, 1], origins_m[v, 2]
        for d in range(dirs.shape[0]):
            dx, dy, dz = dirs[d, 0], dirs[d, 1], dirs[d, 2]
            last = -1
            for k in range(1, nsteps):
                px = ox + dx * k * step
                py = oy + dy * k * step
                pz = oz + dz * k * step
                qx = rot[0, 0] * px + rot[0, 1] * py + rot[0, 2] * pz + trans[0]
                qy = rot[1, 0] * px + rot[1, 1] * py + rot[1, 2] * pz + trans[1]
                qz = rot[2, 0] * px + rot[2, 1] * py + rot[2, 2] * pz + trans[2]
                ix = int(np.floor(qx / wres + 0.5))
                iy = int(np.floor(qy / wres + 0.5))
                iz = int(np.floor(qz / wres + 0.5))
                if ix < 0 or iy < 0 or iz < 0 or ix >= wx or iy >= wy or iz >= wz:
                    break
                cx = int(np.floor(px / res + 0.5)) - offset[0]
                cy = int(np.floor(py / res + 0.5)) - offset[1]
                cz = int(np.floor(pz / res + 0.5)) - offset[2]
                if cx < 0 or cy < 0 or cz < 0 or cx >= mx or cy >= my or cz >= mz:
                    break
                flat = (cx * my + cy) * mz + cz
                if solid[ix, iy, iz]:
                    hits[cx, cy, cz] += 1
                    break
                if flat != last:
                    misses[cx, cy, cz] += 1
                    last = flat


MAX_TILT_DEG = 3.0
"""Roll and pitch of a drawn start frame are uniform within +-this: a drone started on uneven ground."""


def random_frame(rng, start_xy, max_tilt_deg: float = MAX_TILT_DEG, height_m: float = 1.5) -> np.ndarray:
    """world_from_map of a drone's start frame (docs/method.md §1: its pose at the first odometry
    sample): at the start point, within 1 m of start_xy, any yaw, roll/pitch up to max_tilt_deg."""
    yaw = rng.uniform(0, 2 * np.pi)
    roll, pitch = np.radians(rng.uniform(-max_tilt_deg, max_tilt_deg, 2))
    start = np.array([*(np.asarray(start_xy) + rng.uniform(-1.0, 1.0, 2)), height_m])
    return rigid(euler_to_matrix(roll, pitch, yaw), start)


def free_viewpoints(world: World, box_m, count: int, rng) -> np.ndarray:
    """World points (metres) at flight height in free space inside the box, at least 0.4 m from solids."""
    res = world.resolution
    lo = np.maximum((np.asarray(box_m[0]) / res).astype(int), 0)
    hi = np.minimum((np.asarray(box_m[1]) / res).astype(int), np.array(world.solid.shape[:2]) - 1)
    z0, z1 = int(1.0 / res), int(1.9 / res)
    pts = []
    for _ in range(count * 50):
        x, y = rng.integers(lo[0], hi[0] + 1), rng.integers(lo[1], hi[1] + 1)
        z = rng.integers(z0, z1)
        r = int(0.4 / res)
        if not world.solid[max(x - r, 0):x + r + 1, max(y - r, 0):y + r + 1, z - r:z + r + 1].any():
            pts.append([x, y, z])
            if len(pts) == count:
                break
    return np.asarray(pts, dtype=np.float64) * res


def partial_map(world: World, world_from_map: np.ndarray, box_m, rng, viewpoints: int = 14,
                rays: int = 6000, max_range: float = 6.0, pose_noise_m: float = 0.02,
                flip_fraction: float = 0.002) -> PartialMap:
    """Ray-cast map of the explored box, expressed in the frame world_from_map, with mapping noise."""
    res = world.resolution
    vw = free_viewpoints(world, box_m, viewpoints, rng)
    map_from_world = invert(world_from_map)
    vm = apply(map_from_world, vw)
    lo = np.floor((vm.min(axis=0) - max_range) / res).astype(np.int64)
    hi = np.ceil((vm.max(axis=0) + max_range) / res).astype(np.int64)
    shape = tuple(int(v) for v in hi - lo + 1)
    hits = np.zeros(shape, dtype=np.int32)
    misses = np.zeros(shape, dtype=np.int32)
    dirs = fibonacci_directions(rays)
    for v in range(len(vm)):
        # each viewpoint has its own small odometry error, as a drifting drone would
        noise = rigid(euler_to_matrix(0, 0, rng.normal(0, np.radians(0.2))), rng.normal(0, pose_noise_m, 3))
        wfm = world_from_map @ noise
        _cast(world.solid, res, vm[v:v + 1], dirs, wfm[:3, :3].copy(), wfm[:3, 3].copy(), max_range,
              hits, misses, lo, res)
    cells = np.full(shape, UNKNOWN, dtype=CELL_DTYPE)
    free = (misses > 0) & (hits == 0)
    occ = hits > 0
    cells[free] = rng.integers(0, 31, int(free.sum()))
    cells[occ] = rng.integers(70, 101, int(occ.sum()))
    known = np.flatnonzero(cells.reshape(-1) != UNKNOWN)
    flip = rng.choice(known, int(flip_fraction * len(known)), replace=False)
    flat = cells.reshape(-1)
    flat[flip] = np.where(flat[flip] >= 50, rng.integers(0, 31, len(flip)), rng.integers(70, 101, len(flip)))
    grid = OccupancyGrid(cells, res, lo).shrunk()
    return PartialMap(grid, world_from_map, box_m)


def known_overlap(a: PartialMap, b: PartialMap) -> float:
    """|known A ∩ known B| / min(|known A|, |known B|), measured in the world frame."""
    from coopd.grid import transform_grid

    wa = transform_grid(a.grid, a.world_from_map)
    wb = transform_grid(b.grid, b.world_from_map)
    ka, kb = wa.cells != UNKNOWN, wb.cells != UNKNOWN
    lo = np.maximum(wa.offset, wb.offset)
    hi = np.minimum(wa.offset + wa.shape, wb.offset + wb.shape)
    if np.any(hi <= lo):
        return 0.0
    sa = tuple(slice(int(l_ - o), int(h - o)) for l_, h, o in zip(lo, hi, wa.offset, strict=True))
    sb = tuple(slice(int(l_ - o), int(h - o)) for l_, h, o in zip(lo, hi, wb.offset, strict=True))
    inter = int((ka[sa] & kb[sb]).sum())
    return inter / max(1, min(int(ka.sum()), int(kb.sum())))


def make_pair(world: World, seed: int, shift_m: float, box_size_m: float = 10.0, **map_kw) -> MergePair:
    """Two partial maps whose explored boxes are box_size_m wide and shift_m apart (controls overlap)."""
    rng = np.random.default_rng(seed)
    ext = np.array(world.solid.shape[:2]) * world.resolution
    for _ in range(100):
        ang = rng.uniform(0, 2 * np.pi)
        d = shift_m * np.array([np.cos(ang), np.sin(ang)])
        ca = rng.uniform(box_size_m / 2 + 0.5, ext - box_size_m / 2 - 0.5)
        cb = ca + d
        if np.all(cb >= box_size_m / 2 + 0.5) and np.all(cb <= ext - box_size_m / 2 - 0.5):
            break
    half = box_size_m / 2
    ma = partial_map(world, random_frame(rng, ca), (ca - half, ca + half), rng, **map_kw)
    mb = partial_map(world, random_frame(rng, cb), (cb - half, cb + half), rng, **map_kw)
    return MergePair(ma.grid, mb.grid, invert(ma.world_from_map) @ mb.world_from_map,
                     known_overlap(ma, mb), seed)


def benchmark_pairs(count: int = 40, seed: int = 7, world_seed: int = 0, non_overlapping: int = 10,
                    **map_kw) -> list[MergePair]:
    """The merge benchmark: `count` overlapping pairs (box shifts 3-8.5 m: overlap about 0.15-0.65)
    plus `non_overlapping` pairs of small boxes 16 m apart, which must be rejected."""
    world = make_world(world_seed)
    rng = np.random.default_rng(seed)
    shifts = rng.uniform(3.0, 8.5, count)
    pairs = [make_pair(world, seed * 1000 + i, float(s), **map_kw) for i, s in enumerate(shifts)]
    pairs += [make_pair(world, seed * 1000 + count + i, 16.0, box_size_m=6.0, **map_kw)
              for i in range(non_overlapping)]
    return pairs


def make_chain(world: World, seed: int, centres_xy, box_size_m: float = 8.0, **map_kw) -> list[PartialMap]:
    """Partial maps of boxes centred at the given points, each in its own random frame (multi-map)."""
    rng = np.random.default_rng(seed)
    half = box_size_m / 2
    boxes = [(np.asarray(c) - half, np.asarray(c) + half) for c in centres_xy]
    return [partial_map(world, random_frame(rng, c), box, rng, **map_kw)
            for c, box in zip(centres_xy, boxes, strict=True)]

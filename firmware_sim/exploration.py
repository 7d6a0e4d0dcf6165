"""Whole-building explorations ray-cast from a world's analytic ground truth (the thesis' merge input).

A drone explores a whole building: viewpoints every ~0.8 m along the world's closed loop at a flight
altitude, each with a small pose error, rays over the whole sphere up to a maximum range. The cells
a ray crosses become free, the cell it stops in occupied, the rest stays unknown. The map is cast
directly in its own frame (any yaw and translation in the world), with coopd's ray-cast kernel of
firmware_sim/benchset.py, so the truth transform between two maps is exact: no resampling.

`table5_pairs` builds the thesis' Table 5 experiment (two explorations of each of the six worlds, map
B's frame turned 180 degrees and 7-10 m away from A's, both merge orders); `turned_copies` the
thesis' turned / noisy copies of one map. Maps are cached as .npz under out/thesis_set/.
"""

from __future__ import annotations

import hashlib
import io
import math
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
from scipy import ndimage

from coopd.geometry import apply, invert, rigid, rotation_z
from coopd.grid import OccupancyGrid, transform_grid
from coopd.grid.cells import CELL_DTYPE, UNKNOWN
from coopd.io.atomic import write_atomic
from firmware_sim.benchset import _cast, fibonacci_directions
from firmware_sim.worlds import GENERATORS, World, build_world, point_on_loop

WORLDS = tuple(GENERATORS)
"""The six firmware_sim worlds, in the thesis' order."""
CACHE_DIR = Path("out/thesis_set")
CACHE_VERSION = 1
"""Part of every cache key: bump it when the maps a parameter set produces change."""
FREE_VALUES = (0, 31)
OCCUPIED_VALUES = (70, 101)
"""Occupancy values (half-open ranges) of free and occupied cells, as in benchset."""


@dataclass(frozen=True)
class Route:
    """How one exploration is flown and sensed. Distances in metres, angles in degrees."""

    altitude_m: float = 1.2
    spacing_m: float = 0.8
    """Distance between viewpoints along the loop (rounded so they spread evenly over it)."""
    start_offset_m: float = 0.0
    """Arc length along the loop of the first viewpoint."""
    rays: int = 6000
    """Rays per viewpoint, spread evenly over the sphere."""
    max_range_m: float = 6.0
    pose_noise_m: float = 0.02
    pose_noise_deg: float = 0.2
    """Per-viewpoint position error (per axis) and yaw error, standard deviations."""
    resolution: float = 0.1


@dataclass(frozen=True)
class Exploration:
    """One whole-building map in its own frame and where that frame sits in the world."""

    world: str
    grid: OccupancyGrid
    world_from_map: np.ndarray
    viewpoints_w: np.ndarray
    """(k, 3) world positions the map was cast from (before pose noise)."""


@dataclass(frozen=True)
class ThesisPair:
    """Two maps to merge and the exact transform carrying b's frame into a's (metres)."""

    name: str
    kind: str
    """'table5' (two explorations) or 'turned' (a turned, possibly noisy, copy of one map)."""
    world: str
    a: OccupancyGrid
    b: OccupancyGrid
    a_from_b: np.ndarray
    angle_deg: float | None = None
    flip_fraction: float | None = None


def loop_viewpoints(world: World, route: Route) -> np.ndarray:
    """World points every ~route.spacing_m along the world's closed loop at route.altitude_m."""
    length = world.loop_length()
    count = max(1, int(round(length / route.spacing_m)))
    step = length / count
    xy = [point_on_loop(world.loop, route.start_offset_m + k * step)[0] for k in range(count)]
    return np.array([[x, y, route.altitude_m] for x, y in xy], dtype=np.float64)


def _map_box(occ_shape, origin, world_from_map, viewpoints_m, route: Route):
    """Cell-key box (lo, shape) of the map frame that rays can reach: the viewpoints +- range, cut
    to the ground truth's bounds as seen from the map frame."""
    res = route.resolution
    lo_w = origin - res / 2
    hi_w = origin + (np.asarray(occ_shape) - 0.5) * res
    corners = np.array([[x, y, z] for x in (lo_w[0], hi_w[0]) for y in (lo_w[1], hi_w[1])
                        for z in (lo_w[2], hi_w[2])])
    world_in_map = apply(invert(world_from_map), corners)
    lo = np.maximum(viewpoints_m.min(axis=0) - route.max_range_m, world_in_map.min(axis=0))
    hi = np.minimum(viewpoints_m.max(axis=0) + route.max_range_m, world_in_map.max(axis=0))
    lo_key = np.floor(lo / res).astype(np.int64) - 1
    hi_key = np.ceil(hi / res).astype(np.int64) + 1
    return lo_key, tuple(int(v) for v in hi_key - lo_key + 1)


def occupancy_from_counts(hits: np.ndarray, misses: np.ndarray, rng) -> np.ndarray:
    """Cells of a ray-cast map: occupied where a ray stopped, free where rays only passed."""
    cells = np.full(hits.shape, UNKNOWN, dtype=CELL_DTYPE)
    free = (misses > 0) & (hits == 0)
    occupied = hits > 0
    cells[free] = rng.integers(*FREE_VALUES, int(free.sum()))
    cells[occupied] = rng.integers(*OCCUPIED_VALUES, int(occupied.sum()))
    return cells


def explore(world: World, world_from_map: np.ndarray, route: Route, seed: int) -> Exploration:
    """Ray-cast one whole-building exploration of the world in the frame world_from_map."""
    rng = np.random.default_rng(seed)
    res = route.resolution
    occ, origin = world.ground_truth(res)
    views_w = loop_viewpoints(world, route)
    keys = np.floor((views_w - origin) / res + 0.5).astype(np.int64)
    inside = np.all((keys >= 0) & (keys < occ.shape), axis=1)
    clear = inside.copy()
    clear[inside] = ~occ[tuple(keys[inside].T)]
    views_w = views_w[clear]  # a viewpoint inside a solid would see nothing
    views_m = apply(invert(world_from_map), views_w)
    lo_key, shape = _map_box(occ.shape, origin, world_from_map, views_m, route)
    hits = np.zeros(shape, dtype=np.int32)
    misses = np.zeros(shape, dtype=np.int32)
    dirs = fibonacci_directions(route.rays)
    for k in range(len(views_m)):
        # every viewpoint has its own small pose error (a yaw about the sensor and a shift), as a
        # drone's odometry would: the map is drawn from where the drone believes it was
        turn = rigid(rotation_z(rng.normal(0.0, math.radians(route.pose_noise_deg))))
        at = rigid(translation=views_m[k])
        noise = rigid(translation=rng.normal(0.0, route.pose_noise_m, 3)) @ at @ turn @ invert(at)
        wfm = world_from_map @ noise
        # the kernel's world has cell [0,0,0] centred on the origin: fold the ground truth's origin in
        _cast(occ, res, views_m[k:k + 1], dirs, wfm[:3, :3].copy(), wfm[:3, 3] - origin, route.max_range_m,
              hits, misses, lo_key, res)
    grid = OccupancyGrid(occupancy_from_counts(hits, misses, rng), res, lo_key).shrunk()
    return Exploration(world.name, grid, np.asarray(world_from_map, dtype=np.float64), views_w)


def flipped(grid: OccupancyGrid, fraction: float, rng) -> OccupancyGrid:
    """A copy with `fraction` of its known cells flipped, occupied <-> free (salt noise)."""
    cells = grid.cells.copy()
    flat = cells.reshape(-1)
    known = np.flatnonzero(flat >= 0)
    pick = rng.choice(known, int(round(fraction * len(known))), replace=False)
    was_occupied = flat[pick] >= 50
    flat[pick] = np.where(was_occupied, rng.integers(*FREE_VALUES, len(pick)),
                          rng.integers(*OCCUPIED_VALUES, len(pick))).astype(CELL_DTYPE)
    return OccupancyGrid(cells, grid.resolution, grid.offset)


def turned_copies(grid: OccupancyGrid, angles_deg=(37.0, 90.0, 180.0), flips=(0.0, 0.02, 0.05, 0.10),
                  seed: int = 0, shift_m=(2.0, 4.0), world: str = "", name: str = "map") -> list[ThesisPair]:
    """Copies of a map turned by each yaw angle and shifted shift_m (range, rounded to whole cells) in
    a random horizontal direction (transform_grid resamples), then with each fraction of known cells
    flipped. Each pair
    is (a = the map, b = the copy, a_from_b exact); the flip levels of one angle share one turn."""
    rng = np.random.default_rng(seed)
    out = []
    for angle in angles_deg:
        heading = rng.uniform(0.0, 2 * np.pi)
        shift = rng.uniform(*shift_m) * np.array([np.cos(heading), np.sin(heading), 0.0])
        # whole cells: a turn by a multiple of 90 deg then carries cell centres onto cell centres, so
        # such a copy is lossless and its truth exact (a half-cell shift would bias it by 0.05 m)
        shift = np.round(shift / grid.resolution) * grid.resolution
        copy_from_map = rigid(rotation_z(math.radians(angle)), shift)
        turned = transform_grid(grid, copy_from_map)
        for fraction in flips:
            b = flipped(turned, fraction, rng) if fraction > 0 else turned
            out.append(ThesisPair(f"{name}:turn{angle:g}:flip{fraction:g}", "turned", world, grid, b,
                                  invert(copy_from_map), float(angle), float(fraction)))
    return out


def pair_frames(world: World, first_view_w: np.ndarray, rng, distance_m=(7.0, 10.0),
                turn_deg: float = 180.0) -> tuple[np.ndarray, np.ndarray]:
    """world_from_map of A (at its first viewpoint, random yaw) and of B: A's frame turned by
    turn_deg in yaw and moved distance_m (range) horizontally (thesis Table 6: 180 deg, 9 m)."""
    a = rigid(rotation_z(rng.uniform(0.0, 2 * np.pi)), first_view_w)
    heading = rng.uniform(0.0, 2 * np.pi)
    d = rng.uniform(*distance_m) * np.array([np.cos(heading), np.sin(heading), 0.0])
    return a, a @ rigid(rotation_z(math.radians(turn_deg)), d)


def world_explorations(name: str, seed: int = 0, routes: tuple[Route, Route] | None = None,
                       cache_dir: Path | None = CACHE_DIR) -> tuple[Exploration, Exploration]:
    """The two explorations A and B of one world (cached): A at 1.2 m from the loop's start, B at
    1.6 m from half-way round with its viewpoints in between A's, B's frame turned 180 degrees."""
    world = build_world(name, seed)
    if routes is None:
        spacing = Route().spacing_m
        routes = (Route(altitude_m=1.2), Route(altitude_m=1.6,
                                               start_offset_m=world.loop_length() / 2 + spacing / 2))
    path = None
    if cache_dir is not None:
        path = Path(cache_dir) / f"{name}_s{seed}_{cache_key(routes)}.npz"
        if path.exists():
            return load(path, name)
    rng = np.random.default_rng([seed, WORLDS.index(name) if name in WORLDS else 99])
    frame_a, frame_b = pair_frames(world, loop_viewpoints(world, routes[0])[0], rng)
    seeds = rng.integers(0, 2**31, 2)
    maps = tuple(explore(world, frame, route, int(s))
                 for frame, route, s in zip((frame_a, frame_b), routes, seeds, strict=True))
    if path is not None:
        save(maps, path)
    return maps


def table5_pairs(worlds=WORLDS, seed: int = 0, cache_dir: Path | None = CACHE_DIR) -> list[ThesisPair]:
    """The thesis' Table 5 experiment: per world two explorations, merged both ways (A<-B, B<-A)."""
    out = []
    for name in worlds:
        a, b = world_explorations(name, seed, cache_dir=cache_dir)
        a_from_b = invert(a.world_from_map) @ b.world_from_map
        out.append(ThesisPair(f"{name}:A<-B", "table5", name, a.grid, b.grid, a_from_b))
        out.append(ThesisPair(f"{name}:B<-A", "table5", name, b.grid, a.grid, invert(a_from_b)))
    return out


def occupied_points(grid: OccupancyGrid) -> np.ndarray:
    """Centres (metres, map frame) of the grid's occupied cells."""
    return (np.argwhere(grid.cells >= 50) + grid.offset) * grid.resolution


def landing_agreement(a: OccupancyGrid, b: OccupancyGrid, a_from_b: np.ndarray) -> float:
    """Share of b's occupied cells on vertical structure (an occupied cell straight above or below:
    floors agree under any horizontal shift) that, carried into a's frame, land within one cell (26
    neighbours) of an occupied cell of a, among those landing on cells a knows: near 1 for the truth."""
    near = ndimage.binary_dilation(a.cells >= 50, structure=np.ones((3, 3, 3), dtype=bool))
    occ = b.cells >= 50
    stacked = np.zeros_like(occ)
    stacked[:, :, 1:] |= occ[:, :, :-1]
    stacked[:, :, :-1] |= occ[:, :, 1:]
    points = (np.argwhere(occ & stacked) + b.offset) * b.resolution
    keys = np.floor(apply(a_from_b, points) / a.resolution + 0.5).astype(np.int64) - a.offset
    keys = keys[np.all((keys >= 0) & (keys < a.shape), axis=1)]
    known = a.cells[tuple(keys.T)] >= 0
    return float(near[tuple(keys[known].T)].mean()) if known.any() else 0.0


def cache_key(routes) -> str:
    """Short digest of everything that decides the maps (routes and the cache version)."""
    text = repr((CACHE_VERSION, [sorted(asdict(r).items()) for r in routes]))
    return hashlib.sha1(text.encode()).hexdigest()[:12]


def save(maps, path: Path) -> None:
    """Write explorations to one .npz, atomically (readers see the old file or the new one)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    arrays = {}
    for i, m in enumerate(maps):
        arrays |= {f"m{i}_cells": m.grid.cells, f"m{i}_offset": m.grid.offset,
                   f"m{i}_resolution": np.float64(m.grid.resolution),
                   f"m{i}_world_from_map": m.world_from_map, f"m{i}_viewpoints": m.viewpoints_w}
    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)
    write_atomic(path, buf.getvalue())


def load(path: Path, name: str) -> tuple[Exploration, ...]:
    """Read explorations written by save()."""
    with np.load(path) as z:
        count = len([k for k in z.files if k.endswith("_cells")])
        return tuple(Exploration(name, OccupancyGrid(z[f"m{i}_cells"].copy(), float(z[f"m{i}_resolution"]),
                                                     z[f"m{i}_offset"].copy()),
                                 z[f"m{i}_world_from_map"].copy(), z[f"m{i}_viewpoints"].copy())
                     for i in range(count))

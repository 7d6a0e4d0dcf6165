"""Merge pairs from any firmware_sim world (the six or a generated one): two drones' partial maps.

Each map is what benchset's ray-caster makes of a 10 m box of the world's analytic ground truth
(firmware_sim/benchset.py: 14 viewpoints in free space at flight height, 6000 rays each, 6 m range,
2 cm / 0.2 deg pose noise per viewpoint, 0.2 % flipped cells), cast directly in the map's own start
frame (any yaw, roll/pitch <= 3 deg), so the truth transform is exact. The two boxes are centred on
the world's exploration loop, `shift_m` apart in a straight line, which sets the overlap.

Variants of map B measure robustness to real differences between drones: B mapped at another
resolution ('res0.05', 'res0.2': cast on the ground truth voxelised at that resolution), B's drone
started higher ('lift1': its map frame 1 m above A's start height), and 10 % of B's known cells
flipped ('flip0.1').
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass

import numpy as np

from coopd.geometry import apply, invert, rigid
from coopd.grid import OccupancyGrid
from firmware_sim import benchset
from firmware_sim.exploration import flipped
from firmware_sim.worlds import World, point_on_loop

BOX_M = 10.0
LOOP_STEP_M = 0.25


@dataclass(frozen=True)
class WorldPair:
    """Two partial maps of one world and the exact transform carrying b's frame into a's."""

    world: str
    seed: int
    variant: str
    """'base' or the difference map B carries ('res0.05', 'res0.2', 'lift1', 'flip0.1')."""
    a: OccupancyGrid
    b: OccupancyGrid
    a_from_b: np.ndarray
    overlap: float
    """Known-cell overlap of the base pair (benchset.known_overlap: over the smaller map)."""


def displacement(estimate: np.ndarray, truth: np.ndarray, points: np.ndarray) -> tuple[float, float]:
    """(mean, max) distance in metres between the points carried by the estimated and by the true
    transform: the error a merged map shows, whatever the lever arm to the frame's origin."""
    if len(points) == 0:
        shift = float(np.linalg.norm(estimate[:3, 3] - truth[:3, 3]))
        return shift, shift
    d = np.linalg.norm(apply(estimate, points) - apply(truth, points), axis=1)
    return float(d.mean()), float(d.max())


class _Voxels:
    """The world's ground truth as benchset's ray-caster wants it, per resolution: a boolean grid
    whose cell [0, 0, 0] is centred on the kernel frame's origin, and where that origin is in the world."""

    def __init__(self, world: World) -> None:
        self.world = world
        self._cache: dict[float, tuple[benchset.World, np.ndarray]] = {}

    def at(self, resolution: float) -> tuple[benchset.World, np.ndarray]:
        """(kernel world, world position of its origin) at this resolution."""
        if resolution not in self._cache:
            occ, origin = self.world.ground_truth(resolution)
            self._cache[resolution] = (benchset.World(occ, resolution), origin)
        return self._cache[resolution]

    def cast(self, world_from_map: np.ndarray, centre_xy, rng, resolution: float = 0.1,
             **map_kw) -> benchset.PartialMap:
        """A partial map of the BOX_M box around centre_xy in the frame world_from_map (world metres)."""
        kernel, origin = self.at(resolution)
        to_kernel = rigid(translation=-origin)
        half = BOX_M / 2
        box = (np.asarray(centre_xy) - half - origin[:2], np.asarray(centre_xy) + half - origin[:2])
        return benchset.partial_map(kernel, to_kernel @ world_from_map, box, rng, **map_kw)


def _loop_points(world: World) -> np.ndarray:
    """Points every LOOP_STEP_M along the world's loop."""
    return np.array([point_on_loop(world.loop, s)[0]
                     for s in np.arange(0.0, world.loop_length(), LOOP_STEP_M)])


def box_centres(world: World, rng, shift_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Two points of the loop: a random one, and one as close to shift_m away (straight line) as the
    loop offers (a random one among those within 0.5 m of that distance)."""
    pts = _loop_points(world)
    ca = pts[int(rng.integers(len(pts)))]
    gap = np.abs(np.linalg.norm(pts - ca, axis=1) - shift_m)
    near = np.flatnonzero(gap <= 0.5)
    cb = pts[int(rng.choice(near))] if len(near) else pts[int(np.argmin(gap))]
    return ca, cb


def world_pairs(world: World, seed: int, shift_m: float, variants=(), voxels: _Voxels | None = None,
                max_tilt_deg: float = benchset.MAX_TILT_DEG, **map_kw) -> list[WorldPair]:
    """The base pair of two boxes shift_m apart, then one pair per B variant (same boxes and frames).
    max_tilt_deg bounds the roll and pitch of each start frame (0: both drones started level)."""
    voxels = voxels or _Voxels(world)
    rng = np.random.default_rng(seed)
    ca, cb = box_centres(world, rng, shift_m)
    frame_a = benchset.random_frame(rng, ca, max_tilt_deg)
    frame_b = benchset.random_frame(rng, cb, max_tilt_deg)
    ma = voxels.cast(frame_a, ca, rng, **map_kw)
    mb = voxels.cast(frame_b, cb, rng, **map_kw)
    base_overlap = benchset.known_overlap(ma, mb)
    pairs = [WorldPair(world.name, seed, "base", ma.grid, mb.grid, invert(frame_a) @ frame_b, base_overlap)]
    for name in variants:
        vr = np.random.default_rng([seed, zlib.crc32(name.encode())])  # the same whatever else is asked
        if name.startswith("res"):
            b = voxels.cast(frame_b, cb, vr, resolution=float(name[3:]), **map_kw).grid
            truth = invert(frame_a) @ frame_b
        elif name.startswith("lift"):
            lifted = rigid(translation=[0.0, 0.0, float(name[4:])]) @ frame_b
            b = voxels.cast(lifted, cb, vr, **map_kw).grid
            truth = invert(frame_a) @ lifted
        elif name.startswith("flip"):
            b, truth = flipped(mb.grid, float(name[4:]), vr), invert(frame_a) @ frame_b
        else:
            raise ValueError(f"unknown pair variant {name!r} (res<m>, lift<m>, flip<fraction>)")
        pairs.append(WorldPair(world.name, seed, name, ma.grid, b, truth, base_overlap))
    return pairs

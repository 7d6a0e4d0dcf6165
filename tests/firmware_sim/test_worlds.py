"""Worlds: deterministic generation, loadable MJCF, ground-truth grids, start poses and routes."""

from __future__ import annotations

import math

import mujoco
import numpy as np
import pytest

from firmware_sim.shapes import Box, Cylinder
from firmware_sim.voxelize import voxelize
from firmware_sim.worlds import GENERATORS, build_world

WORLDS = sorted(GENERATORS)


def cell_of(origin: np.ndarray, p, res: float) -> tuple[int, int, int]:
    """Index of the cell containing world point p."""
    return tuple(int(i) for i in np.floor((np.asarray(p) - (origin - res / 2)) / res))


@pytest.mark.parametrize("name", WORLDS)
def test_world_is_deterministic_and_loads(name):
    a, b = build_world(name, seed=3), build_world(name, seed=3)
    assert a.mjcf == b.mjcf
    m = mujoco.MjModel.from_xml_string(a.mjcf)
    assert m.ngeom == len(a.shapes) > 5


@pytest.mark.parametrize("name", WORLDS)
def test_seed_changes_the_world(name):
    assert build_world(name, seed=1).mjcf != build_world(name, seed=2).mjcf


@pytest.mark.parametrize("name", WORLDS)
def test_ground_truth_fraction_and_floor(name):
    w = build_world(name, seed=0)
    occ, origin = w.ground_truth(0.1)
    frac = occ.mean()
    assert 0.03 < frac < 0.25, frac
    # The floor slab (z in [-0.1, 0]) is the bottom layer and covers the world's interior.
    kz = cell_of(origin, (0, 0, -0.05), 0.1)[2]
    assert kz == 0
    interior = occ[5:-5, 5:-5, 0]
    assert interior.mean() > 0.99
    # Nothing exists above the world's height bound.
    assert occ.shape[2] * 0.1 <= w.bounds_max[2] - w.bounds_min[2] + 0.2


def test_small_house_known_objects():
    w = build_world("small_house", seed=0)
    occ, origin = w.ground_truth(0.1)
    sofa = next(s for s in w.shapes if s.name.startswith("sofa_"))
    c = cell_of(origin, sofa.center, 0.1)
    assert occ[c]
    lo, hi = sofa.bounds()
    above = cell_of(origin, (sofa.center[0], sofa.center[1], hi[2] + 0.55), 0.1)
    assert not occ[above]
    # A wall: the outer wall at x in [-0.1, 0] is occupied full height; 0.5 m inside is free at 1.5 m.
    assert occ[cell_of(origin, (-0.05, 5.0, 1.5), 0.1)]
    assert not occ[cell_of(origin, (3.0, 2.5, 1.5), 0.1)]
    # Wall height 2.7 m: occupied at 2.65, free at 2.75.
    assert occ[cell_of(origin, (-0.05, 5.0, 2.65), 0.1)]
    assert not occ[cell_of(origin, (-0.05, 5.0, 2.75), 0.1)]


def test_bookstore_round_table_is_round():
    w = build_world("bookstore", seed=0)
    occ, origin = w.ground_truth(0.05)
    top = next(s for s in w.shapes if s.name.startswith("roundtable_"))
    x, y, z = top.center
    k = cell_of(origin, (x, y, z), 0.05)[2]
    layer = occ[:, :, k]
    ix, iy = cell_of(origin, (x, y, z), 0.05)[:2]
    r_cells = int(top.radius / 0.05)
    disc = layer[ix - r_cells - 3 : ix + r_cells + 4, iy - r_cells - 3 : iy + r_cells + 4]
    area = disc.sum() * 0.05**2
    assert abs(area - math.pi * top.radius**2) / (math.pi * top.radius**2) < 0.15
    # Corners of the bounding square are free: it is a disc, not a box.
    assert not occ[cell_of(origin, (x + 0.65, y + 0.65, z), 0.05)]


def test_voxelize_box_is_exact_on_aligned_grid():
    box = Box("b", (0.5, 0.5, 0.5), (0.3, 0.2, 0.1))
    occ, origin = voxelize([box], (0, 0, 0), (1, 1, 1), 0.1)
    assert occ.sum() == 6 * 4 * 2
    np.testing.assert_allclose(origin, [0.05, 0.05, 0.05])
    assert occ[2, 3, 4] and not occ[1, 3, 4] and not occ[2, 3, 6]


def test_voxelize_thin_wall_is_not_missed():
    wall = Box("w", (0.5, 0.52, 0.5), (0.5, 0.01, 0.5))  # 2 cm thick, off the cell centres
    occ, _ = voxelize([wall], (0, 0, 0), (1, 1, 1), 0.1)
    assert occ[:, 5, :].all() and occ.sum() == 100


def test_voxelize_cylinder_touching_cells():
    cyl = Cylinder("c", (0.5, 0.5, 0.5), 0.05, 0.5)  # radius half a cell, centred on a corner
    occ, _ = voxelize([cyl], (0, 0, 0), (1, 1, 1), 0.1)
    assert occ[:, :, 3].sum() == 4


@pytest.mark.parametrize("name", WORLDS)
def test_start_poses_are_clear_and_separated(name):
    w = build_world(name, seed=0)
    poses = w.start_poses(6)
    for i, p in enumerate(poses):
        assert w.is_clear(p[0], p[1], 0.5)
        for q in poses[i + 1 :]:
            assert math.hypot(p[0] - q[0], p[1] - q[1]) >= 1.0


@pytest.mark.parametrize("name", WORLDS)
def test_routes_keep_clear_of_geometry(name):
    w = build_world(name, seed=0)
    occ, origin = w.ground_truth(0.1)
    n = 3
    for i in range(n):
        route = w.route(i, n)
        assert len(route) >= 4
        for a, b in zip(route[:-1], route[1:], strict=True):
            steps = max(2, int(np.linalg.norm(b - a) / 0.05))
            for s in np.linspace(0, 1, steps):
                p = a + s * (b - a)
                assert w.is_clear(p[0], p[1], 0.3), (name, i, p)
                assert not occ[cell_of(origin, p, 0.1)]


def test_unknown_world_and_bad_size_rejected():
    with pytest.raises(ValueError):
        build_world("moon")
    with pytest.raises(ValueError):
        build_world("maze", size=100)


def test_size_scales_hospital():
    small, big = build_world("hospital", 0, size=0.5), build_world("hospital", 0, size=1.5)
    assert big.bounds_max[0] > 2 * small.bounds_max[0]

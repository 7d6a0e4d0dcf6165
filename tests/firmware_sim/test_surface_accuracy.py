"""firmware_sim.accuracy's surface metric: distances to analytic shapes, a perfect voxelisation,
a map offset by a known amount, recall over seen points, free space and ray samples."""

from types import SimpleNamespace

import numpy as np
import pytest

from firmware_sim.accuracy import (
    free_share,
    ray_samples,
    surface_accuracy,
    surface_distance,
)
from firmware_sim.shapes import Cylinder, box_from_corners

RES = 0.1
WALL = box_from_corners("wall", (2.0, -1.0, 0.0), (2.2, 1.0, 2.0))
POST = Cylinder("post", (0.0, 3.0, 1.0), 0.3, 1.0)


IDENTITY = np.eye(4)


def surface_map(points):
    """A perfect voxelisation of a surface: occupied exactly the cells holding one of its (dense)
    points, the rest of the box free. Cell key k is centred at k * RES, as in coopd's grids."""
    keys = np.round(np.asarray(points) / RES).astype(np.int64)
    lo = keys.min(axis=0) - 3
    cells = np.zeros(keys.max(axis=0) + 4 - lo, np.int8)
    cells[tuple((keys - lo).T)] = 100
    return SimpleNamespace(cells=cells, offset=lo, resolution=RES)


def moved(dx):
    """The map frame dx metres along world x."""
    t = np.eye(4)
    t[0, 3] = dx
    return t


def surface_points(n=4000, seed=0):
    """Points on the wall's front face (x = 2.0) and on the post's side."""
    rng = np.random.default_rng(seed)
    wall = np.c_[np.full(n, 2.0), rng.uniform(-1, 1, n), rng.uniform(0, 2, n)]
    a = rng.uniform(0, 2 * np.pi, n)
    post = np.c_[0.3 * np.cos(a), 3.0 + 0.3 * np.sin(a), rng.uniform(0, 2, n)]
    return np.vstack([wall, post])


def test_surface_distance_of_box_and_cylinder():
    pts = np.array([[1.5, 0.0, 1.0],     # 0.5 m in front of the wall
                    [2.05, 0.0, 1.0],    # inside the wall, 0.05 m behind its front face
                    [2.1, 0.0, 3.0],     # 1 m above the wall's top
                    [0.0, 3.0, 1.0],     # the post's axis: 0.3 m inside
                    [1.0, 3.0, 1.0]])    # 0.7 m from the post's side
    assert surface_distance(pts, [WALL, POST]) == pytest.approx([0.5, 0.05, 1.0, 0.3, 0.7])


def test_perfect_voxelisation_scores_one():
    grid = surface_map(surface_points(40_000, seed=1))
    acc = surface_accuracy(grid, IDENTITY, [WALL, POST], surface_points())
    assert acc["surface_precision"] == 1.0 and acc["surface_recall"] == 1.0
    assert acc["surface_p95_m"] <= np.sqrt(3) / 2 * RES + 1e-9
    assert acc["occupied_cells"] > 0 and acc["seen_points"] == 8000


@pytest.mark.parametrize("shift_m", [0.3, 0.5])
def test_map_offset_by_a_known_amount_gives_that_distance(shift_m):
    """The wall's front face (x = 2.0, on cell centres) mapped exactly, the map then moved shift_m
    away from the wall: every occupied cell centre is shift_m from the true surface."""
    front = surface_points(40_000, seed=1)[:40_000]
    acc = surface_accuracy(surface_map(front), moved(-shift_m), [WALL], surface_points()[:4000])
    assert acc["surface_mean_m"] == pytest.approx(shift_m, abs=1e-9)
    assert acc["surface_p95_m"] == pytest.approx(shift_m, abs=1e-9)
    assert acc["surface_precision"] == 0.0 and acc["surface_recall"] == 0.0


def test_one_cell_of_slack_but_not_two():
    grid = surface_map(surface_points(40_000, seed=1)[:40_000])
    acc = surface_accuracy(grid, moved(-0.1), [WALL], surface_points()[:4000])
    assert acc["surface_precision"] == 1.0 and acc["surface_recall"] == 1.0
    acc = surface_accuracy(grid, moved(-0.2), [WALL], surface_points()[:4000])
    assert acc["surface_precision"] == 0.0 and acc["surface_recall"] == 0.0
    turned = np.eye(4)             # a quarter turn about z: the map frame's x is the world's y
    turned[:3, :3] = [[0, -1, 0], [1, 0, 0], [0, 0, 1]]
    grid = surface_map(surface_points(40_000, seed=1)[:40_000] @ turned[:3, :3])
    acc = surface_accuracy(grid, turned, [WALL], surface_points()[:4000])
    assert acc["surface_precision"] == 1.0 and acc["surface_recall"] == 1.0


def test_recall_counts_seen_surfaces_the_map_lacks():
    """A map of the wall alone holds none of the post's surface: recall over both is one half."""
    grid = surface_map(surface_points(40_000, seed=1)[:40_000])
    acc = surface_accuracy(grid, IDENTITY, [WALL, POST], surface_points())
    assert acc["surface_precision"] == 1.0 and acc["surface_recall"] == pytest.approx(0.5)


def test_clutter_lowers_precision():
    grid = surface_map(surface_points(40_000, seed=1)[:40_000])
    n_occ = int((grid.cells >= 50).sum())
    free = np.argwhere(grid.cells == 0)
    clutter = free[np.linspace(0, len(free) - 1, n_occ // 4).astype(int)]
    grid.cells[tuple(clutter.T)] = 100
    d = surface_distance((clutter + grid.offset) * RES, [WALL])
    acc = surface_accuracy(grid, IDENTITY, [WALL], surface_points()[:4000])
    near = np.sum(d <= RES + 1e-9)
    assert near < len(clutter) / 2
    assert acc["surface_precision"] == pytest.approx((n_occ + near) / (n_occ + len(clutter)))


def test_empty_map():
    grid = SimpleNamespace(cells=np.full((4, 4, 4), -1, np.int8), offset=np.zeros(3, np.int64),
                           resolution=RES)
    acc = surface_accuracy(grid, IDENTITY, [WALL], surface_points()[:10])
    assert acc["occupied_cells"] == 0 and acc["surface_precision"] == 0.0 and acc["surface_recall"] == 0.0


def test_free_share_reads_the_map_in_its_frame():
    grid = surface_map(surface_points(40_000, seed=1)[:40_000])    # free from x = 1.7 to 1.95
    assert free_share(grid, IDENTITY, np.array([[1.8, 0.0, 1.0], [1.9, 0.5, 0.5]])) == 1.0
    assert free_share(grid, IDENTITY, np.array([[2.0, 0.0, 1.0], [50.0, 0.0, 0.0]])) == 0.0
    assert free_share(grid, moved(-0.2), np.array([[2.0, 0.0, 1.0]])) == 1.0


def test_ray_samples_keep_surface_within_range_and_clear_free_points():
    origins = np.zeros((3, 3)) + [0.0, 0.0, 1.0]
    dirs = np.array([[1.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    hits = np.array([2.0, 2.0, np.inf])
    surface, free = ray_samples(origins, dirs, hits, max_range=1.5, step=0.1, shapes=[WALL], clearance=0.1)
    assert len(surface) == 0                       # the wall at 2 m is beyond max range
    surface, free = ray_samples(origins, dirs, hits, max_range=5.0, step=0.1, shapes=[WALL], clearance=0.1)
    assert np.allclose(surface, [[2.0, 0.0, 1.0]] * 2)
    assert np.all(surface_distance(free, [WALL]) > 0.1)
    along_x = free[free[:, 1] == 0.0]
    assert along_x[:, 0].max() < 1.9 + 1e-9 and len(along_x) == 2 * 18   # 0.1 .. 1.8 m, twice
    assert free[:, 1].min() == pytest.approx(-4.9)  # the third ray, no hit: free up to max range

"""OBSTACLE_DISTANCE sectors from the grid: exact distances of known walls, unknown -> NO_DATA, known
free -> max + 1, the band, yaw and FRD conventions, the window read, and the numpy reference."""

import math

import numpy as np
import pytest

from coopd.grid import OCCUPIED_THRESHOLD, OccupancyGrid
from coopd.grid.sectors import (
    NO_DATA,
    SECTORS,
    band_keys,
    overlay,
    read_window,
    sector_distances_of,
    window_cells,
    window_keys,
)
from tests.grid.sector_reference import reference_sectors

RES = 0.1
MIN_D, MAX_D = 0.2, 4.0
FREE_BEYOND = int(MAX_D * 100) + 1


def free_room(shape=(120, 120, 30)) -> OccupancyGrid:
    """Known free everywhere (12 x 12 x 3 m around the origin, z keys -15..14)."""
    g = OccupancyGrid.empty(shape, RES)
    g.cells[...] = 5
    return g


def put(g: OccupancyGrid, x0, x1, y0, y1, z0=-15, z1=14, value=90) -> None:
    """Set the inclusive key box (x, y, z keys) to value."""
    g.block((x0, y0, z0), (x1, y1, z1))[...] = value


def sectors(g: OccupancyGrid, position=(0.0, 0.0, 0.0), yaw=0.0, below=0.3, above=0.3,
            min_d=MIN_D, max_d=MAX_D) -> np.ndarray:
    """The kernel on a window read like the daemon reads it, checked against the reference."""
    zk = band_keys(position[2], below, above, g.resolution)
    lo, hi = window_keys(position[0], position[1], zk, max_d, g.resolution)
    window = read_window(g, lo, hi)
    got = sector_distances_of(window, lo, g.resolution, position, yaw, min_d, max_d, OCCUPIED_THRESHOLD)
    want = reference_sectors(g, zk, position, yaw, min_d, max_d, OCCUPIED_THRESHOLD)
    np.testing.assert_array_equal(got, want)
    return got


def test_wall_ahead_and_to_the_right_exact_distances():
    g = free_room()
    put(g, 20, 20, -30, 30)  # wall x = 2.0 m (face at 1.95 m) across y -3..3 m
    put(g, -30, 10, -15, -15)  # wall y = -1.5 m (face at -1.45 m) from x -3 to 1 m
    d = sectors(g)
    assert d.dtype == np.uint16 and d.shape == (SECTORS,)
    assert d[0] == 195  # forward (east): the wall's face
    assert d[18] == 145  # 90 degrees clockwise = right (south in ENU, vehicle facing east)
    assert d[36] == FREE_BEYOND  # behind: known free up to max range
    assert d[54] == FREE_BEYOND  # left
    # off the straight line the nearest point of the wall cells in the sector is farther
    assert 195 < d[4] < 215
    assert d.min() == 145


def test_yawed_north_east_sees_an_east_wall_at_the_front_right():
    g = free_room()
    put(g, 20, 20, -60, 59)  # wall x = 2.0 m across the whole room
    d = sectors(g, yaw=math.radians(45.0))
    assert d[9] == 195  # east is 45 degrees clockwise of north-east
    assert d.min() == 195 and all(d[9 - k] == d[9 + k] for k in range(1, 9))  # symmetric about it
    # straight ahead the wall is further: the sector's near edge (42.5 degrees off the wall's normal)
    assert 195 / math.cos(math.radians(42.5)) - 10 < d[0] < 195 / math.cos(math.radians(45))
    assert d[27] == FREE_BEYOND  # north-west side: free


def test_unknown_map_is_no_data_never_free():
    g = OccupancyGrid.empty((100, 100, 20), RES)
    assert np.all(sectors(g) == NO_DATA)
    # a vehicle off the map entirely
    assert np.all(sectors(free_room(), position=(40.0, 40.0, 0.0)) == NO_DATA)


def test_known_free_reads_max_range_plus_one():
    assert np.all(sectors(free_room()) == FREE_BEYOND)


def test_one_unknown_layer_in_the_band_makes_a_column_unknown():
    g = free_room()
    put(g, 20, 20, -60, 59)
    put(g, 10, 10, -1, 1, 1, 1, value=-1)  # 1 m ahead, one layer of the band never observed
    d = sectors(g)
    assert d[0] == NO_DATA  # unknown before the wall: the sector does not claim the wall is all
    put(g, 10, 10, -1, 1, 1, 1, value=5)
    put(g, 30, 30, -1, 1, 1, 1, value=-1)  # unknown behind the wall does not matter
    assert sectors(g)[0] == 195


def test_unknown_above_the_band_is_outside_it():
    g = free_room()
    put(g, 10, 12, -3, 3, 5, 14, value=90)  # an obstacle 0.5 m above the vehicle and higher
    put(g, -15, -13, -3, 3, -15, -5, value=-1)  # unknown floor-level cells behind
    d = sectors(g, below=0.3, above=0.3)
    assert np.all(d == FREE_BEYOND)
    assert sectors(g, above=0.6)[0] == 95  # a taller band sees it


def test_obstacles_nearer_than_min_range_are_the_vehicle_itself():
    g = free_room()
    put(g, 1, 1, -1, 1)  # a column at 0.05 m: within min range
    assert np.all(sectors(g) == FREE_BEYOND)


def test_walls_beyond_max_range_are_not_reported():
    g = free_room()
    put(g, 45, 45, -60, 59)  # face at 4.45 m
    assert sectors(g)[0] == FREE_BEYOND


def test_band_keys():
    assert band_keys(1.0, 0.3, 0.3, 0.1) == (7, 13)
    assert band_keys(1.04, 0.01, 0.01, 0.1) == (10, 10)  # thinner than a cell: the cell holding z


def test_read_window_fills_what_the_grid_does_not_reach_with_unknown():
    g = free_room((20, 20, 10))  # keys -10..9, z -5..4
    lo, hi = np.array([5, 5, 0]), np.array([14, 14, 2])
    w = read_window(g, lo, hi)
    assert w.shape == (10, 10, 3) and window_cells(lo, hi) == 300
    assert np.all(w[:5, :5] == 5) and np.all(w[5:] == -1) and np.all(w[:, 5:] == -1)
    older = np.full_like(w, 90)
    assert np.all(overlay(w.copy(), older)[5:] == 90)
    assert np.all(overlay(w.copy(), older)[:5, :5] == 5)  # the fresher map wins where it knows


@pytest.mark.parametrize("seed", range(6))
def test_kernel_agrees_with_the_reference_on_random_maps(seed):
    rng = np.random.default_rng(seed)
    g = OccupancyGrid.empty((90, 80, 12), RES)
    choice = rng.choice([-1, -2, 0, 10, 49, 50, 90], size=g.shape, p=[.1, .01, .5, .2, .04, .05, .1])
    g.cells[...] = choice.astype(np.int8)
    for _ in range(5):
        pos = (rng.uniform(-6, 6), rng.uniform(-6, 6), rng.uniform(-0.8, 0.8))
        sectors(g, pos, yaw=rng.uniform(-4, 4), min_d=rng.uniform(0.1, 0.5), max_d=rng.uniform(1.0, 5.0))

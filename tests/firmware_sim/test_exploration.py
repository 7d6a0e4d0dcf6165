"""Whole-building explorations: they see the world, their truth transforms hold, copies and flips."""

import math

import numpy as np
import pytest
from scipy import ndimage
from scipy.spatial import cKDTree

from coopd.geometry import apply, invert, rigid, rotation_angle_deg, rotation_z
from firmware_sim import exploration
from firmware_sim.exploration import Route, landing_agreement, occupied_points, turned_copies
from firmware_sim.worlds import build_world

QUICK = ("small_house", "bookstore")
"""Worlds whose two maps cast in about a second; the others are marked slow."""
SLOW_WORLD = [pytest.mark.slow, pytest.mark.cpu_bound]
WORLDS = [w if w in QUICK else pytest.param(w, marks=SLOW_WORLD) for w in exploration.WORLDS]


@pytest.fixture(scope="module")
def explorations(tmp_path_factory):
    """world name -> (A, B), cast once per test module into a private cache."""
    cache = tmp_path_factory.mktemp("thesis_set")
    made = {}

    def get(name):
        if name not in made:
            made[name] = exploration.world_explorations(name, 0, cache_dir=cache)
        return made[name]

    return get


def solid_near(world, points_w):
    """Whether each world point lies within one cell (26 neighbours) of the ground truth's solid."""
    occ, origin = world.ground_truth(0.1)
    occ = np.pad(occ, 2)
    near = ndimage.binary_dilation(occ, structure=np.ones((3, 3, 3), dtype=bool))
    keys = np.floor((points_w - (origin - 0.2)) / 0.1 + 0.5).astype(np.int64)
    inside = np.all((keys >= 0) & (keys < near.shape), axis=1)
    out = np.zeros(len(points_w), dtype=bool)
    out[inside] = near[tuple(keys[inside].T)]
    return out


def visible_surface(world, viewpoints_w, within_m=3.0):
    """World centres of ground-truth solid cells with a free face neighbour, within within_m of a
    viewpoint: the surface an exploration should have seen (less what furniture hides)."""
    occ, origin = world.ground_truth(0.1)
    surface = occ & ndimage.binary_dilation(~occ)
    points = np.argwhere(surface) * 0.1 + origin
    distance, _ = cKDTree(viewpoints_w).query(points, distance_upper_bound=within_m)
    return points[distance <= within_m]


@pytest.mark.parametrize("name", WORLDS)
def test_exploration_sees_most_of_the_world_and_only_what_is_there(name, explorations):
    world = build_world(name, 0)
    for m in explorations(name):
        surface = visible_surface(world, m.viewpoints_w)
        keys = m.grid.keys_of(apply(invert(m.world_from_map), surface))
        occupied = ndimage.binary_dilation(m.grid.cells >= 50, structure=np.ones((3, 3, 3), dtype=bool))
        inside = m.grid.contains(keys)
        seen = np.zeros(len(keys), dtype=bool)
        seen[inside] = occupied[tuple((keys[inside] - m.grid.offset).T)]
        # racetrack: the far sides of its tyre barriers face the track's outside
        assert seen.mean() >= (0.7 if name == "racetrack" else 0.8), (name, seen.mean())
        assert solid_near(world, apply(m.world_from_map, occupied_points(m.grid))).mean() >= 0.99
        assert len(m.viewpoints_w) >= world.loop_length() / 1.0


@pytest.mark.parametrize("name", WORLDS)
def test_table5_truth_is_a_180_degree_turn_7_to_10_m_away_and_holds(name, explorations):
    a, b = explorations(name)
    truth = invert(a.world_from_map) @ b.world_from_map
    assert abs(rotation_angle_deg(truth[:3, :3]) - 180.0) < 1e-6
    assert 7.0 <= np.linalg.norm(truth[:3, 3]) <= 10.0
    assert landing_agreement(a.grid, b.grid, truth) >= 0.97
    assert landing_agreement(b.grid, a.grid, invert(truth)) >= 0.97
    wrong = truth @ rigid(rotation_z(math.radians(3.0)))
    assert landing_agreement(a.grid, b.grid, wrong) < 0.8  # the check tells a 3 degree error
    # a shift along a long straight wall is ambiguous to this check; across it, it is not
    shifts = ([0.7, 0.0, 0.0], [0.0, 0.7, 0.0])
    shifted = [landing_agreement(a.grid, b.grid, rigid(translation=d) @ truth) for d in shifts]
    assert min(shifted) < 0.8


def test_table5_pairs_are_both_orders_with_inverse_truths(tmp_path):
    pairs = exploration.table5_pairs(("small_house",), cache_dir=tmp_path)
    assert [p.name for p in pairs] == ["small_house:A<-B", "small_house:B<-A"]
    ab, ba = pairs
    assert ab.a is ba.b and ab.b is ba.a and ab.kind == "table5"
    assert np.allclose(ab.a_from_b @ ba.a_from_b, np.eye(4))


def test_cached_maps_read_back_equal_and_the_key_follows_the_route(tmp_path):
    first = exploration.world_explorations("small_house", 0, cache_dir=tmp_path)
    assert len(list(tmp_path.glob("*.npz"))) == 1 and not list(tmp_path.glob("*.tmp"))
    again = exploration.world_explorations("small_house", 0, cache_dir=tmp_path)
    for m, n in zip(first, again, strict=True):
        assert m.grid.same_cells(n.grid) and np.array_equal(m.world_from_map, n.world_from_map)
        assert np.array_equal(m.viewpoints_w, n.viewpoints_w)
    assert exploration.cache_key([Route()]) != exploration.cache_key([Route(rays=3000)])


def test_viewpoints_follow_the_loop_at_the_altitude():
    world = build_world("bookstore", 0)
    views = exploration.loop_viewpoints(world, Route(altitude_m=1.6, spacing_m=0.8))
    steps = np.linalg.norm(np.diff(views[:, :2], axis=0), axis=1)
    assert np.all(views[:, 2] == 1.6) and steps.max() <= 0.8 * 1.05 + 1e-9
    assert abs(len(views) * 0.8 - world.loop_length()) <= 0.8


def test_turned_copies_truth_holds_and_flips_have_the_asked_fraction(explorations):
    a, _ = explorations("small_house")
    copies = turned_copies(a.grid, angles_deg=(37.0, 180.0), flips=(0.0, 0.05, 0.10), seed=3)
    assert [(c.angle_deg, c.flip_fraction) for c in copies] == [
        (37.0, 0.0), (37.0, 0.05), (37.0, 0.1), (180.0, 0.0), (180.0, 0.05), (180.0, 0.1)]
    for c in copies:
        assert c.a is a.grid and c.kind == "turned"
        assert abs(rotation_angle_deg(c.a_from_b[:3, :3]) - c.angle_deg) < 1e-6
        assert 1.9 <= np.linalg.norm(c.a_from_b[:3, 3]) <= 4.1
        shift = invert(c.a_from_b)[:3, 3]
        assert np.allclose(shift / 0.1, np.round(shift / 0.1))  # the copy moved by whole cells
    turned, counts = copies[3].b.counts(), a.grid.counts()  # 180 deg carries every cell onto one: lossless
    assert (turned.free, turned.occupied) == (counts.free, counts.occupied)
    for lossless in (copies[0], copies[3]):
        assert landing_agreement(a.grid, lossless.b, lossless.a_from_b) >= 0.97
        off = rigid(translation=[0.4, 0.4, 0.0]) @ lossless.a_from_b
        assert landing_agreement(a.grid, lossless.b, off) < 0.8
    for base, noisy in ((copies[0], copies[1]), (copies[0], copies[2]), (copies[3], copies[5])):
        before, after = base.b.cells, noisy.b.cells
        assert np.array_equal(before < 0, after < 0)  # only known cells change
        changed = (before >= 50) != (after >= 50)
        assert abs(changed.sum() / (before >= 0).sum() - noisy.flip_fraction) < 1e-4

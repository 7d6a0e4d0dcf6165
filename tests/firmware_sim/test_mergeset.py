"""Merge pairs from firmware_sim worlds: exact truths for the base pair and every variant of map B."""

from __future__ import annotations

import math

import numpy as np
import pytest

from coopd.geometry import rigid, rotation_z
from firmware_sim.exploration import landing_agreement
from firmware_sim.mergeset import box_centres, displacement, world_pairs
from firmware_sim.worlds import build_world


def test_displacement_of_known_offsets():
    points = np.array([[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 3.0, 0.0]])
    truth = rigid(rotation_z(0.3), [2.0, 1.0, 0.5])
    assert displacement(truth, truth, points) == (0.0, 0.0)
    shifted = rigid(translation=[0.0, 0.0, 0.07]) @ truth
    mean, worst = displacement(shifted, truth, points)
    assert mean == pytest.approx(0.07) and worst == pytest.approx(0.07)
    # a small turn about the origin moves far points more: the lever arm
    turned = truth @ rigid(rotation_z(math.radians(1.0)))
    mean, worst = displacement(turned, truth, points)
    step = 2 * math.sin(math.radians(0.5))
    assert worst == pytest.approx(3 * step) and mean == pytest.approx((1 + 1 + 3) * step / 3)
    assert displacement(shifted, truth, np.zeros((0, 3))) == (pytest.approx(0.07), pytest.approx(0.07))


def test_box_centres_lie_on_the_loop_at_the_asked_distance():
    world = build_world("gen:3:outdoor=0,size=30x20")
    rng = np.random.default_rng(0)
    for shift in (3.0, 6.0, 9.0):
        ca, cb = box_centres(world, rng, shift)
        assert abs(np.linalg.norm(cb - ca) - shift) <= 0.5
        assert world.is_clear(*ca, 0.3) and world.is_clear(*cb, 0.3)


def test_world_pairs_truths_are_exact_for_every_variant():
    world = build_world("gen:5:outdoor=0,size=24x16,clutter=1")
    pairs = world_pairs(world, 3, 5.0, ["res0.2", "res0.05", "lift1", "flip0.1"])
    assert [p.variant for p in pairs] == ["base", "res0.2", "res0.05", "lift1", "flip0.1"]
    assert [p.b.resolution for p in pairs] == [0.1, 0.2, 0.05, 0.1, 0.1]
    assert 0.2 < pairs[0].overlap <= 1.0
    assert abs(pairs[3].a_from_b[2, 3] - pairs[0].a_from_b[2, 3] - 1.0) < 0.01  # A tilted by <= 3 deg
    for p in pairs:
        land = landing_agreement(p.a, p.b, p.a_from_b)
        off = landing_agreement(p.a, p.b, rigid(translation=[0.4, 0.3, 0.0]) @ p.a_from_b)
        # flipping 10 % of the known cells adds stray occupied cells anywhere
        assert land > (0.6 if p.variant == "flip0.1" else 0.9), (p.variant, land)
        assert off < land - 0.15, (p.variant, land, off)
    again = world_pairs(world, 3, 5.0, ["lift1"])
    assert again[1].b.same_cells(pairs[3].b) and np.array_equal(again[0].a_from_b, pairs[0].a_from_b)
    with pytest.raises(ValueError, match="unknown pair variant"):
        world_pairs(world, 3, 5.0, ["colour"])


def test_level_start_frames_leave_only_yaw_between_the_maps():
    """max_tilt_deg=0: both drones started level, so the truth turns about the vertical only; the
    boxes and yaws are the ones the tilted draw gives (the same random stream)."""
    world = build_world("gen:5:outdoor=0,size=24x16,clutter=1")
    tilted = world_pairs(world, 3, 5.0)[0]
    level = world_pairs(world, 3, 5.0, max_tilt_deg=0.0)[0]
    assert np.allclose(level.a_from_b[2, :3], [0.0, 0.0, 1.0], atol=1e-12)
    assert not np.allclose(tilted.a_from_b[2, :3], [0.0, 0.0, 1.0], atol=1e-3)
    yaw = [math.atan2(p.a_from_b[1, 0], p.a_from_b[0, 0]) for p in (tilted, level)]
    turn = math.degrees(math.remainder(yaw[0] - yaw[1], 2 * math.pi))
    assert abs(turn) < 0.5, turn  # the same drawn yaws; 3 degrees of tilt move the read yaw a little

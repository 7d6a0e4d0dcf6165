import numpy as np

from coopd.geometry import rotation_angle_deg
from firmware_sim.benchset import make_pair, make_world


def test_world_is_deterministic_and_building_like(world):
    w2 = make_world(0)
    assert np.array_equal(world.solid, w2.solid)
    assert world.solid[:, :, 0].all() and world.solid[:, :, -1].all()  # floor and ceiling
    assert 0.05 < world.solid[:, :, 10].mean() < 0.5  # walls and furniture, mostly free at 1 m


def test_partial_maps_are_ray_cast_in_their_own_frames(world, near_pair):
    p2 = make_pair(world, 101, 3.0)
    assert np.array_equal(p2.a.cells, near_pair.a.cells)
    c = near_pair.a.counts()
    assert c.free > 5 * c.occupied > 0 and c.unknown > 0
    yaw = rotation_angle_deg(near_pair.a_from_b[:3, :3])
    assert yaw > 0.1  # frames differ


def test_overlap_shrinks_as_explored_boxes_move_apart(world):
    ov = [make_pair(world, 7, s).overlap for s in (1.0, 5.0)]
    far = make_pair(world, 7, 16.0, box_size_m=6.0).overlap
    assert ov[0] > ov[1] > far and far < 0.1

import numpy as np
import pytest

from coopd.geometry import euler_to_matrix, invert, rigid, rotation_z
from coopd.grid import OccupancyGrid, fuse_transformed, transform_grid


def _scene_grid(seed=0):
    rng = np.random.default_rng(seed)
    g = OccupancyGrid.empty((60, 60, 20))
    keys = []
    vals = []
    for x in range(-20, 21):                       # an L-shaped wall, free space in front
        for z in range(0, 10):
            keys.append([x, 15, z])
            vals.append(90)
            keys.append([x, 10, z])
            vals.append(10)
    for y in range(-10, 15):
        for z in range(0, 10):
            keys.append([-20, y, z])
            vals.append(95)
    keys = np.array(keys)
    g.set_keys(keys, np.array(vals) + rng.integers(0, 5, len(vals)))
    return g


def test_translation_by_whole_cells_is_exact():
    g = _scene_grid()
    t = rigid(translation=[0.3, -0.5, 0.2])
    moved = transform_grid(g, t)
    k = np.argwhere(g.cells >= 0) + g.offset
    assert np.array_equal(moved.values_at_keys(k + [3, -5, 2]), g.values_at_keys(k))
    assert moved.counts().known == g.counts().known


def test_quarter_turn_is_exact():
    g = _scene_grid()
    moved = transform_grid(g, rigid(rotation_z(np.pi / 2)))
    k = np.argwhere(g.cells >= 0) + g.offset
    rotated = np.stack([-k[:, 1], k[:, 0], k[:, 2]], axis=1)
    assert np.array_equal(moved.values_at_keys(rotated), g.values_at_keys(k))


@pytest.mark.parametrize("yaw,roll,pitch", [(0.3, 0.0, 0.0), (2.5, 0.02, -0.03), (-1.1, 0.05, 0.01)])
def test_round_trip_preserves_known_cells_within_one_cell(yaw, roll, pitch):
    g = _scene_grid()
    t = rigid(euler_to_matrix(roll, pitch, yaw), [1.37, -0.42, 0.11])
    back = transform_grid(transform_grid(g, t), invert(t))
    k = np.argwhere(g.cells >= 0) + g.offset
    orig = g.values_at_keys(k)
    # Every known cell comes back as its own value or that of a cell within one cell.
    offsets = np.array([[dx, dy, dz] for dx in (-1, 0, 1) for dy in (-1, 0, 1) for dz in (-1, 0, 1)])
    ok = np.zeros(len(k), bool)
    for o in offsets:
        ok |= back.values_at_keys(k) == g.values_at_keys(k + o)
    assert ok.mean() > 0.99
    # No wall is lost: every occupied cell still has an occupied cell within one cell.
    occ = k[orig >= 50]
    near_occ = np.zeros(len(occ), bool)
    for o in offsets:
        near_occ |= back.values_at_keys(occ + o) >= 50
    assert near_occ.all()


def test_fuse_transformed_matches_transform_then_fuse():
    a = _scene_grid(1)
    b = _scene_grid(2)
    t = rigid(rotation_z(0.7), [0.5, 0.2, 0.0])
    direct = a.copy()
    n = fuse_transformed(direct, b, t)
    assert n > 0
    from coopd.grid import fuse
    two_step = fuse(a, transform_grid(b, t))
    assert direct.same_cells(two_step)


def test_rejects_non_rigid():
    g = _scene_grid()
    with pytest.raises(ValueError):
        transform_grid(g, np.diag([2.0, 1.0, 1.0, 1.0]))
    with pytest.raises(ValueError):
        transform_grid(g, np.full((4, 4), np.nan))

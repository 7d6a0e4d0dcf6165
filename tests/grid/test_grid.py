import numpy as np
import pytest

from coopd.grid import UNKNOWN, GridTooLarge, GrowthPolicy, OccupancyGrid


def test_flat_index_is_thesis_row_major():
    g = OccupancyGrid.empty((4, 5, 6))
    cells = g.cells
    for x, y, z in [(0, 0, 0), (1, 2, 3), (3, 4, 5), (2, 0, 5)]:
        cells[x, y, z] = 77
        i = z + 6 * (y + 5 * x)
        assert g.flat_index(x, y, z) == i
        assert g.flat[i] == 77
    assert g.size == 4 * 5 * 6


def test_empty_is_centred_and_unknown():
    g = OccupancyGrid.empty((10, 10, 4), resolution=0.2)
    lo, hi = g.key_bounds()
    assert lo.tolist() == [-5, -5, -2] and hi.tolist() == [4, 4, 1]
    assert np.all(g.cells == UNKNOWN)
    assert g.counts().unknown == 400 and g.counts().known == 0


def test_keys_and_centres_round_trip():
    g = OccupancyGrid.empty(resolution=0.1)
    pts = np.array([[0.0, 0.0, 0.0], [0.049, -0.049, 0.051], [1.234, -5.66, 2.0]])
    keys = g.keys_of(pts)
    assert keys.tolist() == [[0, 0, 0], [0, 0, 1], [12, -57, 20]]
    assert np.all(np.abs(g.centres_of(keys) - pts) <= 0.05 + 1e-12)


def test_growth_keeps_origin_centred_and_values():
    policy = GrowthPolicy(margin=2, horizontal_step=10, vertical_step=3)
    g = OccupancyGrid.empty((10, 10, 8), growth=policy)
    g.set_keys([[1, 1, 0]], [90])
    g.set_keys([[9, 0, 0]], [10])           # needs 9+2-4 = 7 more cells in +x
    lo, hi = g.key_bounds()
    # x and y both grew by one step on both sides: origin stays the horizontal centre.
    assert lo[:2].tolist() == [-15, -15] and hi[:2].tolist() == [14, 14]
    assert lo[2] == -4 and hi[2] == 3        # z untouched
    assert g.values_at_keys([[1, 1, 0], [9, 0, 0]]).tolist() == [90, 10]
    g.set_keys([[0, 0, 4]], [60])            # z grows upward only, by whole steps
    lo2, hi2 = g.key_bounds()
    assert lo2[2] == -4 and hi2[2] == 6      # one vertical step of 3 layers, upward only
    assert g.values_at_keys([[1, 1, 0], [0, 0, 4]]).tolist() == [90, 60]


def test_growth_is_bounded():
    g = OccupancyGrid.empty((4, 4, 4), growth=GrowthPolicy(max_cells=10_000))
    before = g.cells.copy()
    with pytest.raises(GridTooLarge):
        g.set_keys([[1000, 0, 0]], [50])
    assert np.array_equal(g.cells, before)


def test_values_outside_are_unknown_and_reading_never_grows():
    g = OccupancyGrid.empty((4, 4, 4))
    assert g.values_at_keys([[100, 100, 100]]).tolist() == [UNKNOWN]
    assert g.shape == (4, 4, 4)


def test_shrink_to_known_bounding_box():
    g = OccupancyGrid.empty((40, 40, 20))
    g.set_keys([[-3, 2, 1], [5, -4, 3]], [100, 0])
    s = g.shrunk()
    assert s.shape == (9, 7, 3)
    assert s.offset.tolist() == [-3, -4, 1]
    assert g.same_cells(s)
    padded = g.shrunk(pad=2)
    assert padded.shape == (13, 11, 7) and g.same_cells(padded)
    assert OccupancyGrid.empty((3, 3, 3)).shrunk().counts().known == 0


def test_copy_is_independent():
    g = OccupancyGrid.empty((4, 4, 4))
    c = g.copy()
    c.set_keys([[0, 0, 0]], [100])
    assert g.values_at_keys([[0, 0, 0]]).tolist() == [UNKNOWN]


def test_counts_classify():
    g = OccupancyGrid.empty((4, 4, 4))
    g.set_keys([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1]], [0, 49, 50, 100, -2])
    c = g.counts()
    assert (c.free, c.occupied, c.inaccessible, c.known, c.total) == (2, 2, 1, 5, g.size)


@pytest.mark.parametrize("bad", [
    dict(cells=np.zeros((2, 2), np.int8), resolution=0.1),
    dict(cells=np.zeros((2, 2, 2), np.int16), resolution=0.1),
    dict(cells=np.zeros((2, 2, 2), np.int8), resolution=float("nan")),
    dict(cells=np.zeros((2, 2, 2), np.int8), resolution=0.0),
])
def test_constructor_rejects_bad_input(bad):
    with pytest.raises(ValueError):
        OccupancyGrid(**bad)

"""resample: a grid at another resolution, same frame, nothing thin lost, nothing thickened."""

import numpy as np
import pytest

from coopd.grid import INACCESSIBLE, UNKNOWN, GrowthPolicy, OccupancyGrid, resample
from coopd.grid.cells import CELL_DTYPE


def _grid(shape, resolution, offset=(0, 0, 0), fill=10):
    return OccupancyGrid(np.full(shape, fill, dtype=CELL_DTYPE), resolution, offset)


def test_same_resolution_is_the_grid_itself():
    g = _grid((4, 4, 4), 0.1)
    assert resample(g, 0.1) is g


def test_coarsening_keeps_a_thin_wall_without_thickening_it():
    g = _grid((40, 40, 20), 0.05, offset=(-20, -20, -3))
    g.cells[17, :, :] = 90  # a wall one fine cell thick at x = (17 - 20) * 0.05 = -0.15 m
    g.cells[:, :, 0] = UNKNOWN
    out = resample(g, 0.1)
    assert out.resolution == 0.1
    occ_x = np.unique(np.argwhere(out.cells >= 50)[:, 0] + out.offset[0])
    assert list(occ_x) == [int(np.floor(-0.15 / 0.1 + 0.5))]  # the one coarse cell holding its centre
    # the coarse cell under every known fine cell's centre is known
    centres = (np.argwhere(g.cells >= 0) + g.offset) * g.resolution
    assert (out.values_at(centres) >= 0).all()
    assert out.values_at(np.array([[-0.15, 0.3, 0.3]]))[0] == 90
    assert out.values_at(np.array([[0.3, 0.3, 0.3]]))[0] == 10


def test_refining_then_coarsening_gives_the_grid_back():
    rng = np.random.default_rng(0)
    cells = rng.choice(np.array([UNKNOWN, INACCESSIBLE, 5, 40, 60, 95], dtype=CELL_DTYPE), size=(9, 7, 5))
    g = OccupancyGrid(cells, 0.1, (-4, 3, -2))
    fine = resample(g, 0.05)
    assert fine.shape == (18, 14, 10)
    for point in ([0.0, 0.3, 0.0], [-0.3, 0.61, 0.11]):  # near coarse centres (fine cells straddle edges)
        assert fine.values_at(np.array([point]))[0] == g.values_at(np.array([point]))[0]
    back = resample(fine, 0.1)
    assert np.array_equal(back.offset, g.offset) and np.array_equal(back.cells, g.cells)


def test_pooling_order_occupied_free_inaccessible_unknown():
    cells = np.array([UNKNOWN, INACCESSIBLE, UNKNOWN, 20, INACCESSIBLE, 70, UNKNOWN, UNKNOWN],
                     dtype=CELL_DTYPE).reshape(8, 1, 1)
    out = resample(OccupancyGrid(cells, 0.05, (0, 0, 0)), 0.1)
    # coarse cell t holds fine centres 2t-1 and 2t: [0], [1, 2], [3, 4], [5, 6], [7]
    assert list(out.cells[:, 0, 0]) == [UNKNOWN, INACCESSIBLE, 20, 70, UNKNOWN]


def test_odd_ratios_and_the_budget():
    g = _grid((30, 30, 10), 0.1, offset=(-15, -15, 0))
    g.cells[5, 5, 5] = 80
    out = resample(g, 0.15)
    assert (out.cells >= 50).sum() == 1
    assert out.values_at(np.array([[-1.0, -1.0, 0.5]]))[0] == 80
    small = OccupancyGrid(g.cells, 0.1, g.offset, GrowthPolicy(max_cells=20_000))
    with pytest.raises(Exception, match="over 20000 cells"):
        resample(small, 0.02)

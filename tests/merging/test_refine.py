"""Refinement: ICP between cell centres, and the sub-cell shift that frees it from lattice minima."""

import numpy as np
import pytest

from coopd.geometry import apply, invert, rigid, rotation_z
from coopd.grid import transform_grid
from coopd.merging.refine import OccupiedCells, icp, subcell_shift


@pytest.fixture(scope="module")
def lossless_copy(near_pair):
    """Map a and a copy turned by 90 degrees and shifted by whole cells: every cell centre of the copy
    lands exactly on one of a's under the truth (a_from_copy)."""
    a = near_pair.a
    copy_from_a = rigid(rotation_z(np.pi / 2), [2.0, -1.3, 0.0])
    return a, transform_grid(a, copy_from_a), invert(copy_from_a)


def _occupied_m(grid):
    return (np.argwhere(grid.cells >= 50) + grid.offset) * grid.resolution


def _target(grid):
    return OccupiedCells(grid.cells >= 50, grid.offset, grid.resolution)


def _displacement(t, truth, points):
    return float(np.linalg.norm(apply(t, points) - apply(truth, points), axis=1).mean())


@pytest.mark.parametrize("slide", [[0.1, 0.0, 0.0], [0.0, -0.1, 0.0], [0.1, 0.1, 0.0], [0.0, 0.0, 0.1]])
def test_subcell_shift_brings_a_transform_a_cell_off_back_onto_the_truth(lossless_copy, slide):
    a, b, truth = lossless_copy
    src = _occupied_m(b)[::10]
    start = truth.copy()
    start[:3, 3] += slide
    t, _ = icp(_target(a), src, start, 28)
    out = subcell_shift(a.cells >= 50, a.offset, a.resolution, src, t)
    print(f"start {slide}: ICP ends {_displacement(t, truth, src):.3f} m off, the shift "
          f"{_displacement(out, truth, src):.3f} m")
    assert _displacement(out, truth, src) <= 0.25 * a.resolution


def test_icp_alone_can_stop_a_cell_away(lossless_copy):
    """Why the shift exists: between two lattices of cell centres, a whole-cell slide along the walls
    is a local minimum of point-to-point ICP (every wall cell has a partner at distance 0)."""
    a, b, truth = lossless_copy
    src = _occupied_m(b)[::10]
    worst = 0.0
    for slide in ([0.1, 0.0, 0.0], [0.0, -0.1, 0.0], [0.1, 0.1, 0.0], [0.0, 0.0, 0.1]):
        start = truth.copy()
        start[:3, 3] += slide
        t, _ = icp(_target(a), src, start, 28)
        worst = max(worst, _displacement(t, truth, src))
    assert worst >= 0.5 * a.resolution


def test_nearest_occupied_cell_is_as_near_as_a_kd_tree_finds(near_pair):
    """The shell search finds, for every point, an occupied cell centre as near as the exact nearest
    one (a k-d tree over all of them), and reports none beyond the radius."""
    from scipy.spatial import cKDTree

    a = near_pair.a
    centres = _occupied_m(a)
    rng = np.random.default_rng(3)
    lo, hi = centres.min(axis=0) - 1.0, centres.max(axis=0) + 1.0
    near_walls = centres[::50] + rng.normal(0.0, 0.07, (len(centres[::50]), 3))
    points = np.concatenate([rng.uniform(lo, hi, (3000, 3)), near_walls])
    for radius in (0.15, 0.6):
        within, nearest = _target(a).nearest(points, radius)
        d_ref, _ = cKDTree(centres).query(points, distance_upper_bound=radius)
        assert np.array_equal(within, np.isfinite(d_ref))
        d = np.linalg.norm(nearest[within] - points[within], axis=1)
        np.testing.assert_allclose(d, d_ref[within], atol=1e-9)
        assert within.sum() > 500

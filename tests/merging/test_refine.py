"""Refinement: ICP between cell centres, and the sub-cell field fit that frees it from lattice minima."""

import numpy as np
import pytest

from coopd.geometry import apply, euler_to_matrix, invert, rigid, rotation_angle_deg, rotation_z
from coopd.grid import transform_grid
from coopd.merging import refine
from coopd.merging.refine import FIELD_SCALE, SIDES, OccupiedCells, facing_fields, field_fit, free_sides, icp


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


def _fit(a, b, t, points=None):
    """field_fit of b's occupied cells (or the given ones) onto a, from t."""
    src = _occupied_m(b) if points is None else points
    normals = free_sides(b.cells, 50, b.offset, b.resolution, src)
    return field_fit(a.cells, a.offset, a.resolution, 50, src, normals, t)


@pytest.mark.parametrize("slide", [[0.1, 0.0, 0.0], [0.0, -0.1, 0.0], [0.1, 0.1, 0.0], [0.0, 0.0, 0.1]])
def test_field_fit_brings_a_transform_a_cell_off_back_onto_the_truth(lossless_copy, slide):
    a, b, truth = lossless_copy
    src = _occupied_m(b)[::10]
    start = truth.copy()
    start[:3, 3] += slide
    t, _ = icp(_target(a), src, start, 28)
    out = _fit(a, b, t).transform
    print(f"start {slide}: ICP ends {_displacement(t, truth, src):.3f} m off, the field fit "
          f"{_displacement(out, truth, src):.3f} m")
    assert _displacement(out, truth, src) <= 0.25 * a.resolution


def _rotation_error_deg(t, truth):
    return rotation_angle_deg(t[:3, :3].T @ truth[:3, :3])


@pytest.mark.parametrize("copy", ["same", "turned"])
def test_field_fit_recovers_a_sub_cell_offset_and_rotation(near_pair, lossless_copy, copy):
    """A map and a copy of it (itself, or turned 90 degrees on the lattice) started 0.03 m and 0.5 deg
    off: the fit ends within 0.01 m and 0.1 deg of the truth."""
    a, b, truth = (near_pair.a, near_pair.a, np.eye(4)) if copy == "same" else lossless_copy
    off = rigid(euler_to_matrix(np.radians(0.2), 0.0, np.radians(0.5)), [0.03, -0.02, 0.01])
    start = off @ truth
    fit = _fit(a, b, start)
    src = _occupied_m(b)
    moved, turned = _displacement(fit.transform, truth, src), _rotation_error_deg(fit.transform, truth)
    print(f"{copy}: start {_displacement(start, truth, src):.3f} m / "
          f"{_rotation_error_deg(start, truth):.2f} deg, fit {moved:.4f} m / {turned:.3f} deg, "
          f"rms {fit.rms_m:.4f} m over {fit.used} points")
    assert moved <= 0.01 and turned <= 0.1
    assert fit.rms_m <= 0.01 and fit.used > 0.9 * len(src)


def test_field_fit_does_not_move_a_right_transform_of_two_drones_maps_far(near_pair):
    """Two ray-cast maps (own noise, partial overlap) started at the exact truth, and within a few
    centimetres and a degree of it: the fit ends within 0.03 m mean displacement of the truth."""
    a, b, truth = near_pair.a, near_pair.b, near_pair.a_from_b
    src = _occupied_m(b)
    rng = np.random.default_rng(5)
    turns = [euler_to_matrix(*np.radians([*rng.uniform(-0.3, 0.3, 2), rng.uniform(-1, 1)])) for _ in range(3)]
    starts = [truth] + [rigid(r, rng.uniform(-0.05, 0.05, 3)) @ truth for r in turns]
    for start in starts:
        fit = _fit(a, b, start)
        print(f"start {_displacement(start, truth, src):.3f} m -> "
              f"{_displacement(fit.transform, truth, src):.4f} m, "
              f"{_rotation_error_deg(fit.transform, truth):.3f} deg")
        assert _displacement(fit.transform, truth, src) <= 0.03


def test_facing_fields_are_the_exact_distance_to_each_sides_cells(near_pair):
    """Every side's field is the Euclidean distance to the centres of the occupied cells facing that
    side (a brute-force distance transform of those cells), clipped at 3 cells, within the uint8 step."""
    from scipy.ndimage import distance_transform_edt

    a = near_pair.a
    lo, shape = np.array([30, 40, 0]), np.array([90, 70, a.cells.shape[2]])
    fields = facing_fields(a.cells, 50, lo, shape, 3.0) / FIELD_SCALE
    occupied = np.argwhere(a.cells >= 50)
    normals = free_sides(a.cells, 50, np.zeros(3, dtype=np.int64), 1.0, occupied.astype(np.float64))
    for side in range(SIDES):
        axis, sign = divmod(side, 2)
        faces = occupied[normals[:, axis] * (1 - 2 * sign) >= 0.38]
        mask = np.ones(a.cells.shape, dtype=bool)
        mask[tuple(faces.T)] = False
        truth = np.minimum(distance_transform_edt(mask), 3.0)[lo[0]:lo[0] + shape[0], lo[1]:lo[1] + shape[1]]
        assert np.abs(fields[side] - truth).max() <= 0.5 / FIELD_SCALE + 1e-6
        assert (fields[side] == 0).sum() > 100


def test_field_fit_is_bounded_on_hostile_inputs(near_pair):
    """Empty, far-off, non-finite and normal-less inputs return the transform given, fitted on nothing."""
    a = near_pair.a
    src = _occupied_m(a)[::20]
    normals = free_sides(a.cells, 50, a.offset, a.resolution, src)
    unknown = np.full((20, 20, 10), -1, dtype=np.int8)
    cases = [(a.cells, src[:0], normals[:0], np.eye(4)),
             (a.cells, src, normals, rigid(translation=[1e6, 0.0, 0.0])),
             (a.cells, src, normals, np.full((4, 4), np.nan)),
             (a.cells, src, np.zeros_like(normals), np.eye(4)),
             (unknown, src, normals, np.eye(4)),
             (a.cells, np.full((5, 3), np.inf), np.ones((5, 3)), np.eye(4)),
             (a.cells[:1, :1, :1], src, normals, np.eye(4))]
    for cells, points, nrm, t in cases:
        fit = field_fit(cells, a.offset, a.resolution, 50, points, nrm, t)
        assert fit.used == 0 and not np.isfinite(fit.rms_m)
        np.testing.assert_array_equal(fit.transform, t)


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
    for radius in (0.15, 0.6, 1.2):
        within, nearest = _target(a).nearest(points, radius)
        d_ref, _ = cKDTree(centres).query(points, distance_upper_bound=radius)
        assert np.array_equal(within, np.isfinite(d_ref))
        d = np.linalg.norm(nearest[within] - points[within], axis=1)
        np.testing.assert_allclose(d, d_ref[within], atol=1e-9)
        assert within.sum() > 500


def testcube_counts_from_the_wrapping_prefix_sums_are_exact():
    """The shell search skips a shell when its cube holds no occupied cell: the count of any cube up
    to MAX_CUBE_HALF, clipped at the grid's faces or wholly outside, is the brute-force count, also
    where the uint16 prefix sums wrapped (a full grid of 60^3 cells)."""
    rng = np.random.default_rng(5)
    for occupied in (rng.random((23, 31, 17)) < 0.03, np.ones((60, 60, 60), dtype=bool)):
        sums, _ = refine.search_index(occupied)
        for _ in range(300):
            centre = rng.integers(-25, np.array(occupied.shape) + 25)
            half = int(rng.integers(0, refine.MAX_CUBE_HALF + 1))
            lo = np.maximum(centre - half, 0)
            hi = np.maximum(np.minimum(centre + half + 1, occupied.shape), lo)
            want = int(occupied[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]].sum())
            assert refine.cube_count(sums, *(int(c) for c in centre), half) == want


def _reference_icp(target, source, t, iterations):
    """ICP written plainly: nearest centres within the shrinking radius, Kabsch on the pairs, stop on
    repeated pairs under the held radius."""
    from coopd.merging.mtm import estimate

    coarse = iterations // 2
    cells = np.concatenate([np.geomspace(6.0, 1.5, coarse), np.full(iterations - coarse, 1.5)])
    radii = cells * target.resolution
    previous, frac = None, 0.0
    for k, r in enumerate(radii):
        ok, nearest = target.nearest(apply(t, source), r)
        frac = float(ok.mean())
        if ok.sum() < 10:
            break
        pairs = np.where(ok[:, None], nearest, np.nan)
        if previous is not None and np.array_equal(pairs, previous, equal_nan=True):
            if k >= coarse:
                break
            continue
        previous = pairs
        t = estimate(source[ok], nearest[ok], False)
    return t, frac


def test_icp_steps_are_the_plain_algorithms(near_pair):
    """icp's compiled step (pairing, the unchanged-pairs test, the fit) gives what the plain loop
    gives, from a start 0.3 m and 4 degrees off: the same pairs at every step (the same inlier
    fraction) and the same transform to 1e-12 (Kabsch compiled inside the step may round its last
    bit differently from Kabsch called alone)."""
    a, b = near_pair.a, near_pair.b
    src = _occupied_m(b)[::7]
    start = rigid(rotation_z(np.radians(4.0)), [0.3, -0.2, 0.05]) @ near_pair.a_from_b
    t, frac = icp(_target(a), src, start, 28)
    t_ref, frac_ref = _reference_icp(_target(a), src, start, 28)
    assert np.abs(t - t_ref).max() < 1e-12 and frac == frac_ref
    assert rotation_angle_deg(t[:3, :3].T @ near_pair.a_from_b[:3, :3]) < 1.0


def test_column_bits_answer_every_z_range_as_the_cells_do():
    """column_holds reads whether a column holds an occupied cell between two heights from the bits,
    across 64-bit words (a grid 150 cells tall) and clipped at the grid's bottom and top."""
    rng = np.random.default_rng(6)
    occupied = rng.random((5, 4, 150)) < 0.01
    _, bits = refine.search_index(occupied)
    for _ in range(2000):
        x, y = int(rng.integers(0, 5)), int(rng.integers(0, 4))
        z0 = int(rng.integers(-10, 160))
        z1 = z0 + int(rng.integers(0, 80))
        want = bool(occupied[x, y, max(z0, 0):max(min(z1 + 1, 150), 0)].any())
        assert refine.column_holds(bits, x, y, z0, z1) == want


def test_nearest_occupied_cell_in_a_tall_sparse_grid_is_the_exact_nearest():
    """The shell search with its skips (empty cubes, empty columns) on a grid taller than one word of
    column bits: the nearest centre within the radius, as a k-d tree finds it."""
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(8)
    occupied = rng.random((30, 25, 140)) < 0.004
    offset = np.array([-7, 3, -60])
    target = OccupiedCells(occupied, offset, 0.1)
    centres = (np.argwhere(occupied) + offset) * 0.1
    points = rng.uniform(centres.min(axis=0) - 0.5, centres.max(axis=0) + 0.5, (4000, 3))
    for radius in (0.15, 0.6):
        within, nearest = target.nearest(points, radius)
        d_ref, _ = cKDTree(centres).query(points, distance_upper_bound=radius)
        assert np.array_equal(within, np.isfinite(d_ref)) and within.sum() > 100
        np.testing.assert_allclose(np.linalg.norm(nearest[within] - points[within], axis=1), d_ref[within],
                                   atol=1e-9)


def test_facing_bits_say_which_side_a_cell_was_seen_from():
    """A wall seen from one side: its cells face that side; a cell with free space all round has no
    side (pairs with any); cells not occupied have no bits."""
    cells = np.full((9, 9, 9), -1, dtype=np.int8)
    cells[:4] = 10  # free space at x < 4
    cells[4] = 80  # a wall at x = 4, seen from -x
    cells[1, 4, 4] = 80  # a speck inside the free space
    bits = refine.facing_bits(cells, 50)
    minus_x = 1 << 1
    assert np.all(bits[4, 1:-1, 1:-1] == minus_x)
    assert bits[1, 4, 4] == refine.ANY_SIDE
    assert np.all(bits[:4][cells[:4] < 50] == 0) and np.all(bits[5:] == 0)


def test_side_bits_of_turned_normals():
    """A point's side bits follow its normal turned into a's frame: +x turned half a turn faces -x, a
    diagonal normal faces two sides, no normal pairs with any side."""
    normals = np.array([[1.0, 0, 0], [np.sqrt(0.5), np.sqrt(0.5), 0], [0, 0, 0]])
    assert refine.side_bits(normals, np.eye(3)).tolist() == [1, 1 | 4, refine.ANY_SIDE]
    assert refine.side_bits(normals, rotation_z(np.pi)[:3, :3]).tolist() == [2, 2 | 8, refine.ANY_SIDE]


def test_nearest_cell_seen_from_the_wanted_side_is_the_exact_nearest():
    """With side bits, the shell search (and its skips) finds the nearest centre among the cells that
    share a bit with the point's, as brute force does; the plain search ignores the bits."""
    rng = np.random.default_rng(9)
    occupied = rng.random((24, 20, 90)) < 0.01
    sides = np.where(occupied, 1 << rng.integers(0, 6, occupied.shape), 0).astype(np.uint8)
    offset = np.array([3, -5, -40])
    target = OccupiedCells(occupied, offset, 0.1, sides)
    keys = np.argwhere(occupied)
    centres = (keys + offset) * 0.1
    points = rng.uniform(centres.min(axis=0) - 0.3, centres.max(axis=0) + 0.3, (1500, 3))
    want = (1 << rng.integers(0, 6, len(points))).astype(np.uint8)
    want[::7] = refine.ANY_SIDE
    within, nearest = target.nearest(points, 0.6, want)
    d = np.linalg.norm(points[:, None, :] - centres[None, :, :], axis=2)
    d[(sides[tuple(keys.T)][None, :] & want[:, None]) == 0] = np.inf
    d_ref = d.min(axis=1)
    d_ref[d_ref > 0.6] = np.inf
    assert np.array_equal(within, np.isfinite(d_ref)) and within.sum() > 300
    np.testing.assert_allclose(np.linalg.norm(nearest[within] - points[within], axis=1), d_ref[within],
                               atol=1e-9)
    plain_within, _ = OccupiedCells(occupied, offset, 0.1).nearest(points, 0.6, want)
    assert plain_within.sum() > within.sum()


def test_icp_pairing_same_facing_cells_stays_at_the_truth(world):
    """On a pair where the drones saw walls from their two sides, ICP started from the truth walks
    0.1 m away pairing any cells, and stays within 0.05 m pairing only cells seen from the same side."""
    from firmware_sim.benchset import make_pair

    pair = make_pair(world, 7, 5.0)
    a, b = pair.a, pair.b
    src = _occupied_m(b)[:: max(1, int((b.cells >= 50).sum()) // 4000)]
    normals = free_sides(b.cells, 50, b.offset, b.resolution, src)
    facing = OccupiedCells(a.cells >= 50, a.offset, a.resolution, refine.facing_bits(a.cells, 50))
    plain, _ = icp(_target(a), src, pair.a_from_b, 28)
    sided, _ = icp(facing, src, pair.a_from_b, 28, normals)
    assert _displacement(plain, pair.a_from_b, src) > 0.08
    assert _displacement(sided, pair.a_from_b, src) < 0.05

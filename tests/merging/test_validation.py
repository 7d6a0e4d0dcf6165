import numpy as np

from coopd.geometry import rigid, rotation_z
from coopd.grid import OccupancyGrid
from coopd.merging.pair import merge_pair
from coopd.merging.params import coopd_params
from coopd.merging.validation import (
    FREE,
    NEAR_OCCUPIED,
    UNSEEN,
    agreement,
    classify,
    loosest_move,
    occupied_indices,
    summarise,
)


def test_classify_marks_free_unknown_and_cells_next_to_occupied():
    cells = np.full((5, 5, 5), 10, dtype=np.int8)
    cells[0] = -1
    cells[2, 2, 2] = 90
    c = classify(cells, 50)
    assert c[0, 0, 0] == UNSEEN and c[4, 4, 4] == FREE
    assert c[1, 1, 1] == NEAR_OCCUPIED and c[3, 3, 3] == NEAR_OCCUPIED and c[4, 2, 2] == FREE


def test_true_transform_scores_high_and_wrong_ones_low(near_pair):
    a = summarise(near_pair.a, 50, 20000, 3)
    b = summarise(near_pair.b, 50, 20000, 3)
    good = agreement(a, b, near_pair.a_from_b)
    assert good.score > 0.95 and good.agree > 5000
    flipped = near_pair.a_from_b @ rigid(rotation_z(np.pi))
    shifted = rigid(None, [2.0, 0.0, 0.0]) @ near_pair.a_from_b
    for wrong in (flipped, shifted):
        bad = agreement(a, b, wrong)
        assert bad.score < 0.9
        assert bad.support(20.0) < good.support(20.0)


def test_occupied_and_vertical_cells_are_listed_as_argwhere_lists_them(near_pair):
    """occupied_indices lists, in one scan, the occupied cells and those in a vertical run of at
    least min_run occupied cells, in np.argwhere's order (the samples validation spreads evenly)."""
    cells = near_pair.a.cells
    occupied = cells >= 50
    for min_run in (2, 3):
        run = np.zeros(occupied.shape, dtype=np.int64)  # length of the run each occupied cell is in
        for x, y in np.argwhere(occupied.any(axis=2)):
            column = occupied[x, y]
            z = 0
            while z < len(column):
                if column[z]:
                    end = z
                    while end < len(column) and column[end]:
                        end += 1
                    run[x, y, z:end] = end - z
                    z = end
                else:
                    z += 1
        listed, vertical = occupied_indices(cells, 50, min_run)
        assert np.array_equal(listed, np.argwhere(occupied))
        assert np.array_equal(vertical, np.argwhere(run >= min_run)) and 0 < len(vertical) < len(listed)


def test_a_two_cell_thick_or_tilted_floor_is_not_vertical_structure():
    """A floor whose plane lies near a cell boundary fills two layers, and a floor tilted by a few
    degrees steps up a cell every few metres (two layers where it steps): runs of two 0.1 m cells,
    which min_run 2 counted as walls. A wall three cells tall is structure."""
    thick = np.zeros((60, 20, 12), dtype=np.int8)
    thick[:, :, 2:4] = 90
    tilted = np.zeros((60, 20, 12), dtype=np.int8)
    for x in range(60):  # tilted by 3 degrees: one cell up every ~1.9 m, two layers at each step
        z = 2 + x // 19
        tilted[x, :, z] = 90
        if x % 19 == 0 and x:
            tilted[x, :, z - 1] = 90
    params = coopd_params()
    assert params.validation_min_run(0.1) == 3 and params.validation_min_run(0.2) == 2
    assert params.validation_min_run(0.12) == 3  # 0.36 m: at least 0.3 m, not 0.24
    for floor in (thick, tilted):
        assert len(occupied_indices(floor, 50, 2)[1]) > 0  # the old rule took them for walls
        assert len(occupied_indices(floor, 50, 3)[1]) == 0
    walled = thick.copy()
    walled[30, :10, 4:7] = 90  # a wall three cells tall on the thick floor
    _, vertical = occupied_indices(walled, 50, params.validation_min_run(0.1))
    assert len(vertical) > 0 and set(vertical[:, 0]) == {30}


def _map(occupied_cells, shape=(80, 80, 16), offset=(-40, -40, -2)):
    """A grid seen all round (free), with the given occupied cells (array indices)."""
    cells = np.full(shape, 0, dtype=np.int8)
    for idx in occupied_cells:
        cells[idx] = 90
    return OccupancyGrid(cells, 0.1, np.array(offset))


def _pole(cx, cy, radius=3, arc_deg=360.0):
    """The cells of a vertical pole's surface seen over arc_deg of its round."""
    return [(cx + dx, cy + dy, slice(2, 14)) for dx in range(-radius, radius + 1)
            for dy in range(-radius, radius + 1)
            if radius - 1 <= np.hypot(dx, dy) <= radius and np.degrees(np.arctan2(dy, dx)) % 360 <= arc_deg]


def test_one_pole_agrees_as_well_turned_and_one_wall_slid_but_a_corner_pins_the_fit():
    pole = summarise(_map(_pole(40, 40)), 50, 20000, 3)
    name, kept = loosest_move(pole, pole, np.eye(4), 20.0, 10.0, 1.0)
    assert "turn" in name and kept > 0.95
    floor_and_pole = _map(_pole(40, 40, radius=5, arc_deg=240) + [(slice(None), slice(None), slice(0, 2))])
    r = merge_pair(floor_and_pole, floor_and_pole)  # a pole seen from one side, on a floor
    assert not r.accepted and r.ambiguous and "turn keeps" in r.reason, r.reason
    wall = summarise(_map([(slice(0, 80), 40, slice(2, 14))]), 50, 20000, 3)  # its ends unseen
    name, kept = loosest_move(wall, wall, np.eye(4), 20.0, 10.0, 1.0)
    assert "along" in name and kept >= 1 - coopd_params().min_margin
    corner = summarise(_map([(slice(10, 70), 40, slice(2, 14)), (10, slice(10, 70), slice(2, 14))]),
                       50, 20000, 3)
    name, kept = loosest_move(corner, corner, np.eye(4), 20.0, 10.0, 1.0)
    assert kept < 0.6


def test_the_agreement_of_either_map_places_the_moves():
    """b saw the wall too low to hold a sample of its own: a's samples that agree in b still show that
    a slide along the wall keeps the support."""
    a = summarise(_map([(slice(0, 80), 40, slice(2, 14))]), 50, 20000, 3)
    low = _map([(slice(0, 80), 40, slice(2, 4))])
    low.cells[:, :, 4:] = -1  # b saw nothing above its two cells of the wall
    b = summarise(low, 50, 20000, 3)
    assert len(b.sample_m) == 0 and agreement(a, b, np.eye(4)).agree > 0
    name, kept = loosest_move(a, b, np.eye(4), 20.0, 10.0, 1.0)
    assert "along" in name and kept >= 1 - coopd_params().min_margin

import numpy as np

from coopd.geometry import rigid, rotation_z
from coopd.merging.validation import (
    FREE,
    NEAR_OCCUPIED,
    UNSEEN,
    agreement,
    classify,
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
    a = summarise(near_pair.a, 50, 20000)
    b = summarise(near_pair.b, 50, 20000)
    good = agreement(a, b, near_pair.a_from_b)
    assert good.score > 0.95 and good.agree > 5000
    flipped = near_pair.a_from_b @ rigid(rotation_z(np.pi))
    shifted = rigid(None, [2.0, 0.0, 0.0]) @ near_pair.a_from_b
    for wrong in (flipped, shifted):
        bad = agreement(a, b, wrong)
        assert bad.score < 0.9
        assert bad.support(20.0) < good.support(20.0)


def test_occupied_and_vertical_cells_are_listed_as_argwhere_lists_them(near_pair):
    """occupied_indices lists, in one scan, the occupied cells and those with an occupied cell
    straight above or below, in np.argwhere's order (the samples validation spreads evenly)."""
    cells = near_pair.a.cells
    occupied = cells >= 50
    stacked = np.zeros_like(occupied)
    stacked[:, :, 1:] |= occupied[:, :, 1:] & occupied[:, :, :-1]
    stacked[:, :, :-1] |= occupied[:, :, :-1] & occupied[:, :, 1:]
    listed, vertical = occupied_indices(cells, 50)
    assert np.array_equal(listed, np.argwhere(occupied))
    assert np.array_equal(vertical, np.argwhere(stacked)) and 0 < len(vertical) < len(listed)

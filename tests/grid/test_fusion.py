import numpy as np
import pytest

from coopd.grid import OccupancyGrid, fuse, fuse_into, fuse_values

U, F, O = -1, 20, 80  # unknown, free, occupied


@pytest.mark.parametrize("a,b,expected_class", [
    (U, U, "unknown"), (U, F, "free"), (U, O, "occupied"),
    (F, U, "free"), (F, F, "free"), (F, O, "occupied"),
    (O, U, "occupied"), (O, F, "occupied"), (O, O, "occupied"),
])
def test_table3_all_nine_cases(a, b, expected_class):
    v = int(fuse_values(np.array([a], np.int8), np.array([b], np.int8))[0])
    got = "unknown" if v == -1 else ("occupied" if v >= 50 else "free")
    assert got == expected_class


def test_fused_probabilities():
    a = np.array([10, 30, 60, 90, -2, -2], np.int8)
    b = np.array([30, 10, 90, 20, 40, -1], np.int8)
    assert fuse_values(a, b).tolist() == [10, 10, 90, 90, 40, -2]
    assert fuse_values(b, a).tolist() == fuse_values(a, b).tolist()  # symmetric


def test_fuse_grids_grows_to_union():
    a = OccupancyGrid.empty((6, 6, 6))
    b = OccupancyGrid.empty((6, 6, 6))
    a.set_keys([[0, 0, 0], [1, 0, 0]], [20, 20])
    b.set_keys([[1, 0, 0], [30, 0, 0]], [90, 10])
    f = fuse(a, b)
    assert f.values_at_keys([[0, 0, 0], [1, 0, 0], [30, 0, 0]]).tolist() == [20, 90, 10]
    assert a.values_at_keys([[1, 0, 0]]).tolist() == [20]  # inputs untouched


def test_fuse_into_requires_same_resolution():
    with pytest.raises(ValueError):
        fuse_into(OccupancyGrid.empty(resolution=0.1), OccupancyGrid.empty(resolution=0.2))

import numpy as np
import pytest

from coopd.geometry import invert, rigid, rotation_angle_deg, rotation_z
from coopd.grid import OccupancyGrid, fuse_transformed
from coopd.merging.multi import merge_all
from firmware_sim.benchset import known_overlap, make_chain


def test_fusion_follows_table_3_under_a_transform():
    """unknown+x = x, free+free = free, occupied wins; checked through a 90 degree yaw + shift."""
    vals = np.array([-1, 10, 90], dtype=np.int8)  # unknown, free, occupied
    a = OccupancyGrid(np.repeat(vals, 3).reshape(9, 1, 1).copy(), 0.1, (0, 0, 0))
    # b's cell at key (0, -i, 0) lands on a's key (i, 0, 0) after a +90 degree yaw and no shift
    b_cells = np.tile(vals, 3)[::-1].reshape(1, 9, 1).copy()
    b = OccupancyGrid(b_cells, 0.1, (0, -8, 0))
    t = rigid(rotation_z(np.pi / 2))
    fuse_transformed(a, b, t)
    got = a.values_at_keys(np.array([[i, 0, 0] for i in range(9)]))
    wa = np.repeat(vals, 3)
    wb = np.tile(vals, 3)
    expect = []
    for x, y in zip(wa, wb, strict=True):
        if x == -1 or y == -1:
            expect.append(max(x, y))
        elif x >= 50 or y >= 50:
            expect.append(max(x, y))
        else:
            expect.append(min(x, y))
    assert got.tolist() == expect


@pytest.mark.slow
@pytest.mark.cpu_bound
def test_region_inheritance_merges_a_map_that_only_overlaps_a_later_one(world):
    maps = make_chain(world, 3, [(6, 12.5), (12, 12.5), (18, 12.5)])
    assert known_overlap(maps[0], maps[2]) < 0.05 < known_overlap(maps[1], maps[2])
    res = merge_all(maps[0].grid, [maps[2].grid, maps[1].grid])
    assert [r.accepted for r in res.results] == [True, True]
    assert res.rounds == 2  # map 2 failed against the reference alone, then merged once map 1 was in
    for m, r in zip([maps[2], maps[1]], res.results, strict=True):
        truth = invert(maps[0].world_from_map) @ m.world_from_map
        assert rotation_angle_deg(r.transform[:3, :3].T @ truth[:3, :3]) < 2.0
        assert np.linalg.norm(r.transform[:3, 3] - truth[:3, 3]) < 0.3
    assert res.global_map.counts().known > 2 * maps[0].grid.counts().known


@pytest.mark.slow
@pytest.mark.cpu_bound
def test_searches_run_ahead_give_the_results_of_one_search_at_a_time(world):
    """With every fit held, two searches at a time give exactly the one-at-a-time results; with fits
    fused, a search that ran ahead on a global map since grown is run again, and the results still
    match."""
    maps = make_chain(world, 4, [(6, 12.5), (10, 12.5), (14, 12.5), (18, 12.5)])
    others = [m.grid for m in maps[1:]]
    for hold in (lambda i, r: True, None):
        alone = merge_all(maps[0].grid, others, hold=hold)
        ahead = merge_all(maps[0].grid, others, hold=hold, ahead=lambda i: True, workers=2)
        assert ahead.full_registrations == alone.full_registrations
        for a, b in zip(alone.results, ahead.results, strict=True):
            assert (a.accepted, a.reason, a.score, a.inliers) == (b.accepted, b.reason, b.score, b.inliers)
            assert np.array_equal(a.transform, b.transform)
        assert np.array_equal(alone.global_map.cells, ahead.global_map.cells)

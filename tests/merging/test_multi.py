from dataclasses import replace

import numpy as np
import pytest

from coopd.geometry import invert, rigid, rotation_angle_deg, rotation_z
from coopd.grid import OccupancyGrid, fuse_transformed
from coopd.merging import multi
from coopd.merging.hints import Hint
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


@pytest.mark.slow
@pytest.mark.cpu_bound
@pytest.mark.parametrize("refusal", ["overlap too small: 0.107 of the maps' structure agrees < 0.2",
                                     "ambiguous: a distinct hypothesis scores 1.000", "score 0.612 < 0.94",
                                     "ambiguous: a 10 deg turn keeps 97% of the support; the overlap does "
                                     "not pin b"])
def test_a_map_the_global_maps_size_refuses_is_searched_on_the_reference_alone(world, monkeypatch, refusal):
    """A map that arrives once others are fused is searched on a global map many times its size. In a
    30-drone swarm the lowest id refused a late map so (its overlap share diluted by the structure far
    from it, score 1.000), and every other drone waited a minute for it. Such a refusal (share alone,
    or ambiguous) is searched again on the reference alone, as the first merge (every fit held) would
    have; any other refusal (disagreement, an overlap that does not pin the map) stands. The global
    map's refusal is forced here, the search after it is real."""
    fused = make_chain(world, 7, [(8, 12.5), (8, 6), (14, 12.5)])
    late = make_chain(world, 8, [(11, 12.5)], box_size_m=4.0)[0]
    ref, rest = fused[0], fused[1:]
    truth = [invert(ref.world_from_map) @ m.world_from_map for m in [*rest, late]]
    real, targets, world_grid = multi.merge_prepared, [], []

    def global_map_refuses(a, b, params, tm=None, known=()):
        r = real(a, b, params, tm, known)
        world_grid[:] = world_grid or [a.grid]  # the late map's first search runs on the global map
        whole = a.grid is world_grid[0]
        targets.append("global" if whole else "reference")
        forced = replace(r, accepted=False, reason=refusal, score=0.612 if "score" in refusal else 1.0)
        return forced if whole else r

    monkeypatch.setattr(multi, "merge_prepared", global_map_refuses)
    res = merge_all(ref.grid, [m.grid for m in [*rest, late]],
                    hints=[[Hint(t, "own")] for t in truth[:-1]] + [[]])
    assert all(r.accepted and r.method == "hint:own" for r in res.results[:-1])
    r = res.results[-1]
    if refusal.startswith("score") or "not pin" in refusal:  # stands: a smaller map pins no better
        assert not r.accepted and r.reason == refusal and set(targets) == {"global"}, targets
        return
    assert r.accepted and targets == ["global", "reference"], (r.reason, targets)
    assert np.linalg.norm(r.transform[:3, 3] - truth[-1][:3, 3]) < 0.1
    assert rotation_angle_deg(r.transform[:3, :3].T @ truth[-1][:3, :3]) < 1.0


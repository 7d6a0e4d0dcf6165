"""Hinted merging: a good hint costs an ICP + validation instead of the search, a wrong or
non-overlapping one is refused and the full search decides; hints_for builds hints from own and
peers' results."""

import time
from types import SimpleNamespace

import numpy as np
import pytest

from coopd.geometry import invert, rigid, rotation_angle_deg, rotation_z
from coopd.merging import Hint, merge_all
from coopd.merging.hints import MAX_HINTS, hints_for
from firmware_sim.benchset import make_chain


def _error(t, truth):
    return float(np.linalg.norm(t[:3, 3] - truth[:3, 3])), rotation_angle_deg(t[:3, :3].T @ truth[:3, :3])


def _cpu(fn):
    t0 = time.thread_time()
    return fn(), time.thread_time() - t0


def _close(t, truth, m=0.3, deg=2.0):
    e_m, e_deg = _error(t, truth)
    return e_m < m and e_deg < deg


@pytest.mark.slow
@pytest.mark.cpu_bound
def test_good_hint_is_accepted_for_less_cpu_than_the_full_search(near_pair):
    full, cpu_full = _cpu(lambda: merge_all(near_pair.a, [near_pair.b]))
    assert full.results[0].accepted and full.results[0].method == "full" and full.full_registrations == 1
    start = rigid(rotation_z(np.radians(1.5)), [0.15, -0.1, 0.0]) @ near_pair.a_from_b  # drifted a bit
    hinted, cpu_hint = _cpu(lambda: merge_all(near_pair.a, [near_pair.b], hints=[[Hint(start)]]))
    r = hinted.results[0]
    assert r.accepted and r.method == "hint:own" and hinted.full_registrations == 0
    assert hinted.hints_refused == [0]
    assert _close(r.transform, near_pair.a_from_b)
    assert cpu_hint < 0.6 * cpu_full, (cpu_hint, cpu_full)
    assert r.to_json()["method"] == "hint:own"


@pytest.mark.slow
@pytest.mark.cpu_bound
@pytest.mark.parametrize("shift, yaw_deg", [(2.0, 0.0), (0.0, 30.0), (3.0, 180.0)])
def test_wrong_hint_is_refused_and_the_full_search_takes_over(near_pair, shift, yaw_deg):
    wrong = rigid(rotation_z(np.radians(yaw_deg)), [shift, 0.0, 0.0]) @ near_pair.a_from_b
    res = merge_all(near_pair.a, [near_pair.b], hints=[[Hint(wrong, "peer")]])
    r = res.results[0]
    assert res.hints_refused == [1] and res.full_registrations == 1 and r.method == "full"
    assert r.accepted and _close(r.transform, near_pair.a_from_b)


@pytest.mark.slow
@pytest.mark.cpu_bound
def test_hint_for_a_map_that_does_not_overlap_is_refused(far_pair):
    res = merge_all(far_pair.a, [far_pair.b], hints=[[Hint(far_pair.a_from_b, "peer")]])
    assert res.hints_refused == [1] and res.full_registrations == 1
    assert not res.results[0].accepted and "overlap" in res.results[0].reason


@pytest.fixture(scope="module")
def chain(world):
    return make_chain(world, 3, [(6.0, 12.5), (10.0, 12.5), (14.0, 12.5)])


def _truth(maps, i, j):
    return invert(maps[i].world_from_map) @ maps[j].world_from_map


@pytest.mark.slow
@pytest.mark.cpu_bound
def test_chained_hints_resolve_through_the_map_they_lean_on(chain):
    """Map 2 gets a hint relative to map 1 (a peer's T_12); it resolves once map 1 merged by its own
    hint (given first in the list but merged after, as the chaining needs)."""
    hints = [[Hint(_truth(chain, 1, 2), "peer", via=1)], [Hint(_truth(chain, 0, 1), "peer")]]
    res = merge_all(chain[0].grid, [chain[2].grid, chain[1].grid], hints=hints)
    assert [r.method for r in res.results] == ["hint:peer", "hint:peer"] and res.full_registrations == 0
    assert _close(res.results[0].transform, _truth(chain, 0, 2))
    assert _close(res.results[1].transform, _truth(chain, 0, 1))


@pytest.mark.slow
@pytest.mark.cpu_bound
def test_a_vouched_chain_is_checked_not_refined_and_a_wrong_one_is_refined_and_refused(chain):
    """Map 2 vouched via map 1 (a peer merged them on the very versions we hold): accepted by the
    check alone, at (map 1's transform) @ the edge, for a fraction of the CPU of refining it. A
    vouched edge turned by 180 degrees fails the check and goes the usual way: refined, refused,
    and the full search places the map."""
    t12, t01 = _truth(chain, 1, 2), _truth(chain, 0, 1)
    maps = [chain[2].grid, chain[1].grid]

    def run(edge, vouched):
        hints = [[Hint(edge, "peer", via=1, vouched=vouched)], [Hint(t01, "peer")]]
        return _cpu(lambda: merge_all(chain[0].grid, maps, hints=hints))

    refined, cpu_refined = run(t12, False)
    checked, cpu_checked = run(t12, True)
    assert checked.vouched == 1 and refined.vouched == 0 and checked.full_registrations == 0
    r = checked.results[0]
    assert r.accepted and r.method == "hint:peer" and r.inliers == 0
    assert np.allclose(r.transform, checked.results[1].transform @ t12)
    assert _close(r.transform, _truth(chain, 0, 2))
    assert cpu_checked < cpu_refined, (cpu_checked, cpu_refined)
    wrong = rigid(rotation_z(np.pi), [0.0, 0.0, 0.0]) @ t12
    res, _ = run(wrong, True)
    assert res.vouched == 0 and res.hints_refused[0] == 1 and res.full_registrations == 1
    assert res.results[0].method == "full" and _close(res.results[0].transform, _truth(chain, 0, 2))


@pytest.mark.slow
@pytest.mark.cpu_bound
def test_a_vouched_direct_edge_is_checked_on_the_reference_and_a_wrong_one_is_refused(chain):
    """A peer's edge to us found on the versions we hold is checked against our own map, not refined:
    accepted at the edge itself. Turned by 180 degrees it fails the check, is refined and refused,
    and the full search places the map."""
    t01 = _truth(chain, 0, 1)
    res = merge_all(chain[0].grid, [chain[1].grid], hints=[[Hint(t01, "peer", vouched=True)]])
    r = res.results[0]
    assert res.vouched == 1 and res.full_registrations == 0
    assert r.accepted and r.method == "hint:peer" and r.inliers == 0 and np.allclose(r.transform, t01)
    wrong = t01 @ rigid(rotation_z(np.pi), [0.0, 0.0, 0.0])
    res = merge_all(chain[0].grid, [chain[1].grid], hints=[[Hint(wrong, "peer", vouched=True)]])
    assert res.vouched == 0 and res.hints_refused[0] == 1 and res.full_registrations == 1
    assert res.results[0].method == "full" and _close(res.results[0].transform, t01)


def _msg(vid, *edges, versions=(0, 0)):
    va, vb = versions
    edge = [SimpleNamespace(a=a, b=b, transform=t, version_a=va, version_b=vb) for a, b, t in edges]
    return SimpleNamespace(vehicle_id=vid, edges=edge)


def test_hints_for_vouches_for_a_chained_edge_only_on_the_versions_we_hold():
    t = rigid(rotation_z(0.2), [1.0, 2.0, 0.0])
    held = {9: 70, 2: 20, 3: 30}
    peers = [_msg(2, (2, 9, t), versions=(20, 70)), _msg(2, (2, 3, t), versions=(20, 30))]
    hints = hints_for(9, [2, 3], {}, peers, held)
    # the peer's direct edge to us and its edge to 3 (which also vouches for 2 via 3)
    assert [(h.via, h.vouched) for h in hints[0]] == [(None, True), (1, True)]
    assert [(h.via, h.vouched) for h in hints[1]] == [(0, True)]
    for stale in ((20, 29), (19, 30)):  # a map changed since the peer merged it
        hints = hints_for(9, [2, 3], {}, [_msg(2, (2, 3, t), versions=stale)], held)
        assert [(h.via, h.vouched) for h in hints[1]] == [(0, False)]
    assert not hints_for(9, [2, 3], {}, peers)[1][0].vouched  # no versions known: never vouched


def test_hints_for_composes_own_direct_and_chained_hints():
    t = {k: rigid(rotation_z(0.1 * k), [k, 2 * k, 0.0]) for k in range(1, 8)}
    own = {2: t[1]}
    peers = [
        _msg(2, (2, 9, t[2]), (2, 3, t[3])),  # 2 merged us (9) and 3
        _msg(3, (3, 4, t[4]), (5, 3, t[5])),  # 3 merged 4; an edge 3 does not own is ignored
        _msg(9, (9, 4, t[6])),  # claims to be us: ignored
        _msg(4, (4, 2, t[7])),  # 4 merged 2: chained hint for 4 via 2 (inverse)
    ]
    hints = hints_for(9, [2, 3, 4], own, peers)
    by = [[(h.source, h.via) for h in hs] for hs in hints]
    # map 2: own first, then 2's edge to us inverted, then through 3 (inverse of T_2,3) and 4 (T_4,2)
    assert by[0] == [("own", None), ("peer", None), ("peer", 1), ("peer", 2)]
    assert np.allclose(hints[0][1].transform, invert(t[2]))
    assert np.allclose(hints[0][2].transform, invert(t[3])) and np.allclose(hints[0][3].transform, t[7])
    assert by[1] == [("peer", 0), ("peer", 2)]  # T_9,3 = T_9,2 @ T_2,3 and T_9,4 @ inv(T_3,4)
    assert np.allclose(hints[1][0].transform, t[3]) and np.allclose(hints[1][1].transform, invert(t[4]))
    assert by[2] == [("peer", 1), ("peer", 0)]
    assert np.allclose(hints[2][0].transform, t[4]) and np.allclose(hints[2][1].transform, invert(t[7]))
    many = [_msg(2, *[(2, 9, t[1])] * 10)]
    assert len(hints_for(9, [2], {}, many)[0]) == MAX_HINTS
    with pytest.raises(ValueError, match="rigid"):
        Hint(np.diag([2.0, 1.0, 1.0, 1.0]))


def test_refused_hints_that_disagree_are_final_those_that_miss_the_map_are_retried(near_pair):
    """try_hints marks a hint that conflicts with the map as final, one that lands off the map is not
    (a larger global map may still hold it): merge_all then retries only the latter after a fuse."""
    from coopd.merging.hints import try_hints
    from coopd.merging.pair import prepare
    from coopd.merging.params import coopd_params

    params = coopd_params()
    pa, pb = prepare(near_pair.a, params, lazy=True), prepare(near_pair.b, params, lazy=True)
    t = near_pair.a_from_b
    flipped, off_map = rigid(rotation_z(np.pi)) @ t, rigid(None, [40.0, 0.0, 0.0]) @ t
    r, refused, final = try_hints(pa, pb, [(flipped, "peer"), (off_map, "peer")], params)
    assert r is None and refused == 2 and final == [0]
    r, refused, final = try_hints(pa, pb, [(off_map, "peer"), (t, "own"), (flipped, "peer")], params)
    # the flipped hint after it is a distinct rival: validated (and refused) for the ambiguity check
    assert r.method == "hint:own" and refused == 2 and final == [] and _close(r.transform, t)


def test_two_distinct_hints_that_both_validate_leave_the_choice_to_the_full_search():
    """A rectangular room fits itself turned by 180 degrees: the true hint and its twin both validate,
    so neither is taken, and the full search refuses the merge as ambiguous (its runner-up margin)."""
    from coopd.grid import OccupancyGrid

    cells = np.full((60, 40, 20), 80, dtype=np.int8)
    cells[2:-2, 2:-2, 2:-2] = 10
    a = OccupancyGrid(cells.copy(), 0.1, (0, 0, 0))
    b = OccupancyGrid(cells.copy(), 0.1, (-30, -20, 0))
    truth = rigid(None, [3.0, 2.0, 0.0])
    centre = np.array([2.95, 1.95, 0.0])
    twin = rigid(None, centre) @ rigid(rotation_z(np.pi)) @ rigid(None, -centre) @ truth
    alone = merge_all(a, [b], hints=[[Hint(twin, "peer")]])
    assert alone.results[0].method == "hint:peer"  # one hint alone cannot see the symmetry
    near = rigid(rotation_z(np.radians(1.0)), [0.2, 0.0, 0.0]) @ truth  # the same hypothesis, drifted
    same = merge_all(a, [b], hints=[[Hint(truth), Hint(near, "peer")]])
    assert same.results[0].method == "hint:own" and same.hints_refused == [0]
    both = merge_all(a, [b], hints=[[Hint(truth), Hint(twin, "peer")]])
    r = both.results[0]
    assert both.hints_refused == [2] and both.full_registrations == 1
    assert not r.accepted and r.reason.startswith("ambiguous")

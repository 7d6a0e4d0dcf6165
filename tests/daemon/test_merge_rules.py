"""The merging thread's rules (coopd.daemon.merge_rules): pure functions, no thread, map or merge_all."""

from types import SimpleNamespace

import numpy as np
import pytest

from coopd.daemon import merge_rules as rules
from coopd.geometry import rigid, rotation_z
from coopd.sharing.wire import EDGE_FULL, MergeEdge

FIT = rigid(rotation_z(0.4), [2.0, 1.0, 0.0])


def _result(accepted=True, method="full", transform=FIT, score=0.9):
    return SimpleNamespace(accepted=accepted, method=method, transform=transform, score=score, overlap=0.3)


# ------------------------------------------------------------------------------------- triggering
def test_requests_settle_after_the_last_one_but_at_most_a_gap_after_the_first():
    assert rules.settled_at(None, 50.0, 2.0, 5.0) == 0.0  # nothing pending
    assert rules.settled_at(10.0, 11.0, 2.0, 5.0) == 13.0  # settle_s after the last
    assert rules.settled_at(10.0, 14.5, 2.0, 5.0) == 15.0  # capped at min_gap_s after the first
    assert rules.settled_at(10.0, 14.5, 8.0, 5.0) == 18.0  # the cap is never below settle_s


def test_maps_of_new_vehicles_still_arriving_extend_the_cap_to_a_few_gaps():
    # a swarm's first exchange spread over 6 s: settle_s after the last new map, not 5 s after the first
    assert rules.settled_at(10.0, 16.0, 2.0, 5.0, last_new_at=16.0) == 18.0
    # updates of maps already merged do not extend it: settle_s after the last new one, or the usual cap
    assert rules.settled_at(10.0, 16.0, 2.0, 5.0, last_new_at=12.0) == 15.0
    assert rules.settled_at(10.0, 16.0, 2.0, 5.0, last_new_at=14.5) == 16.5
    # bounded: new maps that never stop still merge NEW_MAPS_WAIT gaps after the first request
    assert rules.settled_at(10.0, 40.0, 2.0, 5.0, last_new_at=40.0) == 10.0 + rules.NEW_MAPS_WAIT * 5.0
    assert rules.settled_at(None, 40.0, 2.0, 5.0, last_new_at=40.0) == 0.0


def test_peers_alive_whose_maps_have_not_come_hold_a_first_merge_up_to_the_cap():
    cap = 10.0 + rules.NEW_MAPS_WAIT * 5.0
    assert rules.settled_at(10.0, 11.0, 2.0, 5.0, last_new_at=11.0, awaiting=True) == cap
    assert rules.settled_at(10.0, 11.0, 2.0, 5.0, last_new_at=11.0, awaiting=False) == 13.0
    # only a request bringing a new vehicle's map waits for the others: updates merge as before
    assert rules.settled_at(10.0, 11.0, 2.0, 5.0, last_new_at=None, awaiting=True) == 13.0


def test_a_merge_of_unchanged_inputs_is_skipped_unless_something_still_waits():
    inputs = (3, ((2, 1),), ())
    assert rules.skip_as_unchanged(False, inputs, inputs, False, False)
    assert not rules.skip_as_unchanged(True, inputs, inputs, False, False)  # merge-now
    # a search waiting for a peer: nothing to do on unchanged inputs until the wait is over
    assert rules.skip_as_unchanged(False, inputs, inputs, True, False, deferral_over=False)
    assert not rules.skip_as_unchanged(False, inputs, inputs, True, False, deferral_over=True)
    assert not rules.skip_as_unchanged(False, inputs, inputs, True, True, deferral_over=False)  # holding
    assert not rules.skip_as_unchanged(False, inputs, inputs, True, False)  # a search waits for a peer
    assert not rules.skip_as_unchanged(False, inputs, inputs, False, True)  # fits to confirm
    assert not rules.skip_as_unchanged(False, (4, ((2, 1),), ()), inputs, False, False)
    assert not rules.skip_as_unchanged(False, None, None, False, False)  # no local version: always merge


def test_peers_results_are_forgotten_once_nothing_is_left_out():
    inputs = (3, ((2, 1),), ((5, 9),))
    assert rules.inputs_to_remember(inputs, left_out=False) == (3, ((2, 1),), ())
    assert rules.inputs_to_remember(inputs, left_out=True) == inputs
    assert rules.inputs_to_remember(None, left_out=False) is None


def test_a_look_at_held_fits_before_the_gap_merges_only_to_confirm_them():
    held, grown = (3, ((2, 1),), ()), (4, ((2, 1),), ())
    assert not rules.confirm_too_early(False, True, held, held, now=1.0, gap_until=5.0)  # confirm now
    assert rules.confirm_too_early(False, True, grown, held, now=1.0, gap_until=5.0)  # wait for the gap
    assert not rules.confirm_too_early(False, True, grown, held, now=5.0, gap_until=5.0)
    assert not rules.confirm_too_early(True, True, grown, held, now=1.0, gap_until=5.0)  # merge-now
    assert not rules.confirm_too_early(False, False, grown, held, now=1.0, gap_until=5.0)  # nothing held


def test_the_maps_settled_during_a_merge_as_long_as_settle_s_on_unchanged_inputs():
    same = (1, ((2, 5),), ())
    assert rules.settled_during(3.0, 2.0, same, same)
    assert not rules.settled_during(1.0, 2.0, same, same)  # too short to tell
    assert not rules.settled_during(3.0, 2.0, same, (1, ((2, 6),), ()))  # a map changed meanwhile
    assert not rules.settled_during(3.0, 2.0, None, None)


def test_held_fits_are_confirmed_without_a_search_only_on_the_inputs_that_held_them():
    inputs = (3, ((2, 1),), ())
    assert rules.confirms_without_search(True, True, inputs, inputs)
    assert not rules.confirms_without_search(True, True, (4, ((2, 1),), ()), inputs)
    assert not rules.confirms_without_search(False, True, inputs, inputs)  # nothing held
    assert not rules.confirms_without_search(True, False, inputs, inputs)  # no global map to fuse into
    assert not rules.confirms_without_search(True, True, None, None)


# -------------------------------------------------------------------------------- pair decisions
def test_a_pair_has_stopped_growing_below_one_percent_and_never_before_its_first_merge():
    assert rules.stopped_growing(1005, 1000)
    assert not rules.stopped_growing(1010, 1000)
    assert not rules.stopped_growing(1000, 0)


@pytest.mark.parametrize("size, decided_at, last_size, growth, due", [
    (1300, 1000, 1200, 1.3, True),  # grown 1.3x
    (1290, 1000, 1200, 1.3, False),  # still growing, not 1.3x yet
    (1060, 1000, 1055, 1.3, True),  # stopped growing on maps 6 % larger: once more on the final maps
    (1040, 1000, 1035, 1.3, False),  # stopped growing, decided on nearly these maps
    (5000, 1000, 5000, None, False),  # recheck_growth None: never
])
def test_a_pair_is_due_for_a_recheck_once_grown_or_settled_on_larger_maps(size, decided_at, last_size,
                                                                          growth, due):
    assert rules.due_for_recheck(size, decided_at, last_size, growth) is due


def test_only_a_map_with_hints_competes_and_then_when_contested_or_due():
    assert rules.competes(True, contested=True, due=False)
    assert rules.competes(True, contested=False, due=True)
    assert not rules.competes(True, contested=False, due=False)
    assert not rules.competes(False, contested=True, due=True)


@pytest.mark.parametrize("method, new_fit, was_provisional, settled, due, held", [
    ("hint:peer", True, True, False, False, False),  # peers publish confirmed merges only
    ("hint:own", False, True, False, True, True),  # our own provisional fit alone confirms nothing
    ("hint:own", False, True, True, False, False),  # ... until the pair settles
    ("hint:own", False, False, False, False, False),  # a confirmed fit stays confirmed
    ("full", True, False, False, False, True),  # a new fit is held
    ("full", True, True, False, True, True),  # a recheck found another fit: that one is held
    ("full", True, False, True, False, False),  # found on maps that stopped growing: nothing more to wait for
    ("full", False, True, False, True, False),  # the same fit found again on grown maps: confirmed
    ("full", False, True, False, False, True),  # the same fit, maps not grown enough: still held
    ("full", False, False, False, False, False),  # the confirmed fit again
])
def test_which_accepted_fits_are_held_out_of_the_global_map(method, new_fit, was_provisional, settled, due,
                                                           held):
    assert rules.held_provisional(method, new_fit, was_provisional, settled, due) is held


def test_full_searches_wait_for_a_lower_vehicle_id_for_a_bounded_time():
    assert rules.waits_for_peer(5, [1, 2], distributed=True, defer_full_s=30.0)
    assert not rules.waits_for_peer(1, [2, 3], distributed=True, defer_full_s=30.0)  # the lowest id searches
    assert not rules.waits_for_peer(5, [1, 2], distributed=False, defer_full_s=30.0)
    assert not rules.waits_for_peer(5, [1, 2], distributed=True, defer_full_s=0.0)
    assert not rules.waits_for_peer(5, [], distributed=True, defer_full_s=30.0)
    # a lower id alive whose map has not come yet searches too: only maps of higher ids held, we wait
    assert rules.waits_for_peer(5, [7, 9], distributed=True, defer_full_s=30.0, alive=[2, 8])
    assert not rules.waits_for_peer(5, [7], distributed=True, defer_full_s=30.0, alive=[6, 8])
    assert not rules.waits_for_peer(5, [], distributed=True, defer_full_s=30.0, alive=[1])  # nothing to defer
    assert rules.defers_search(False, False, 10.0, 30.0)
    assert not rules.defers_search(True, False, 10.0, 30.0)  # merged here before: its own hint serves
    assert not rules.defers_search(False, True, 10.0, 30.0)  # a hint to validate instead
    assert not rules.defers_search(False, False, 30.0, 30.0)  # waited long enough


# ------------------------------------------------------------------------------------- publishing
def test_an_accepted_result_becomes_an_edge_with_clipped_figures_and_its_origin():
    full = rules.merge_edge(1, 4, 7, 3, _result(score=1.7))
    assert (full.a, full.b, full.version_a, full.version_b, full.flags) == (1, 4, 3, 7, EDGE_FULL)
    assert full.score == 1.0 and full.overlap == 0.3 and np.array_equal(full.transform, FIT)
    assert rules.merge_edge(1, 4, 7, 3, _result(method="hint:own", score=-0.2)).flags == 0


def _edge(b, transform):
    return MergeEdge(1, b, transform, 0.9, 0.3, 1, 1, EDGE_FULL)


def test_edges_count_as_changed_for_other_vehicles_or_a_transform_moved_past_the_tolerance():
    published = {2: FIT}
    assert not rules.edges_changed(published, [_edge(2, FIT)])
    assert not rules.edges_changed(published, [_edge(2, rigid(rotation_z(0.4), [2.015, 1.0, 0.0]))])
    assert rules.edges_changed(published, [_edge(2, rigid(rotation_z(0.4), [2.03, 1.0, 0.0]))])
    assert rules.edges_changed(published, [_edge(2, rigid(rotation_z(0.4 + np.radians(0.3)), [2.0, 1.0, 0]))])
    assert rules.edges_changed(published, [_edge(2, FIT), _edge(3, FIT)])
    assert rules.edges_changed({}, [_edge(2, FIT)])

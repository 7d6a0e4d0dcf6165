"""What the merging thread keeps (coopd.daemon.merge_state): the per-vehicle book, the trigger, the
publisher, the global map slot and the settings, without a merge thread or merge_all."""

import threading
import time
from types import SimpleNamespace

import numpy as np

from coopd.daemon.budget import MemoryBudget
from coopd.daemon.main import build_config, parse_args
from coopd.daemon.merge_state import (
    MERGE_MIN_GAP_S,
    FitBook,
    GlobalMapSlot,
    MergerSettings,
    MergeTrigger,
    ResultPublisher,
)
from coopd.geometry import rigid, rotation_z
from coopd.grid import OccupancyGrid
from coopd.sharing.wire import EDGE_FULL, MergeEdge

FIT = rigid(rotation_z(0.4), [2.0, 1.0, 0.0])
MIRROR = rigid(rotation_z(0.4 + np.pi), [2.0, 1.0, 0.0])


def _result(accepted=True, method="full", transform=FIT, ambiguous=False):
    return SimpleNamespace(accepted=accepted, method=method, transform=transform, ambiguous=ambiguous,
                           score=0.9, overlap=0.3, reason="accepted" if accepted else "ambiguous")


def _map(vid, version=1):
    return SimpleNamespace(vehicle_id=vid, version=version)


def _edge(b, transform):
    return MergeEdge(1, b, transform, 0.9, 0.3, 1, 1, EDGE_FULL)


# -------------------------------------------------------------------------------------- the book
def test_the_book_keeps_accepted_transforms_as_hints_and_the_maps_left_out():
    book = FitBook()
    edges = book.record(1, [_map(2, 5), _map(3)], [_result(), _result(accepted=False)], [1000, 800], set(),
                        None, local_version=9)
    assert [(e.b, e.version_a, e.version_b) for e in edges] == [(2, 9, 5)]
    assert list(book.transforms()) == [2] and book.left_out and book.edges() == edges
    assert book.pair(2).decided_at == 1000 and book.pair(2).last_size == 1000
    book.record(1, [_map(2)], [_result(method="hint:own")], [1400], set(), None, local_version=10)
    assert not book.left_out  # map 3 is gone from the inputs
    assert book.pair(2).decided_at == 1000 and book.pair(2).last_size == 1400  # a hint decides nothing


def test_a_first_accepted_hint_marks_the_size_it_was_decided_on():
    book = FitBook()
    book.record(1, [_map(2)], [_result(method="hint:peer")], [1200], set(), None, local_version=1)
    assert book.pair(2).decided_at == 1200


def test_an_ambiguous_search_drops_the_transform_and_contests_the_map_until_a_search_wins():
    book = FitBook()
    book.record(1, [_map(2)], [_result()], [1000], set(), None, local_version=1)
    book.record(1, [_map(2)], [_result(accepted=False, ambiguous=True)], [1100], set(), None, local_version=2)
    assert book.contested() == [2] and book.transforms() == {}
    assert book.to_contest([2], [["a peer's hint"]], [1100], 1.3) == frozenset({0})
    assert book.to_contest([2], [[]], [1100], 1.3) == frozenset()  # nothing to compete with
    book.record(1, [_map(2)], [_result()], [1150], set(), None, local_version=3)
    assert book.contested() == [] and list(book.transforms()) == [2]


def test_a_map_is_rechecked_once_its_pair_grew():
    book = FitBook()
    book.record(1, [_map(2)], [_result()], [1000], set(), None, local_version=1)
    assert book.to_contest([2], [["own"]], [1200], 1.3) == frozenset()
    assert book.to_contest([2], [["own"]], [1300], 1.3) == frozenset({0})
    assert book.to_contest([2], [["own"]], [1300], None) == frozenset()


def test_a_new_fit_is_held_until_found_again_on_grown_maps_and_then_confirmed():
    book = FitBook()
    assert book.holds(2, _result(), 1000, 1.3)  # never seen: a new fit
    inputs = (1, ((2, 1),), ())
    book.record(1, [_map(2)], [_result()], [1000], {2}, inputs, local_version=1)
    assert book.provisional() == [2] and book.holding and book.held_inputs == inputs
    assert book.holds(2, _result(method="hint:own"), 1200, 1.3)  # our own transform alone: still held
    assert book.holds(2, _result(), 1200, 1.3)  # the same fit, not grown 1.3x: still held
    assert book.holds(2, _result(transform=MIRROR), 1400, 1.3)  # another fit: held in its turn
    assert not book.holds(2, _result(), 1400, 1.3)  # the same fit on 1.4x maps: confirmed
    assert not book.holds(2, _result(method="hint:peer"), 1200, 1.3)
    book.record(1, [_map(2)], [_result()], [1400], set(), inputs, local_version=2)
    assert book.provisional() == [] and not book.holding and book.held_inputs is None


def test_a_search_may_run_ahead_only_where_any_fit_it_finds_would_be_held():
    book = FitBook()
    assert book.holds_any_fit(2, 1000)  # never fitted: its first fit is held
    book.record(1, [_map(2), _map(3)], [_result(), _result(accepted=False)], [1000, 900], {2}, None, 1)
    assert not book.holds_any_fit(2, 1400)  # fitted: the same fit found again on grown maps is fused
    assert book.holds_any_fit(3, 1000)  # refused before, its pair still growing
    assert not book.holds_any_fit(3, 905)  # refused on maps that stopped growing: a fit would settle
    assert book.holds(3, _result(), 1000, 1.3) and not book.holds(3, _result(), 905, 1.3)


def test_confirming_every_held_fit_clears_them_and_their_inputs():
    book = FitBook()
    book.record(1, [_map(2), _map(3)], [_result(), _result()], [1000, 900], {2, 3}, (1, (), ()), 1)
    assert book.confirm_all() == [2, 3]
    assert book.provisional() == [] and book.held_inputs is None
    assert [e.b for e in book.edges()] == [2, 3]  # the edges to publish now


def test_a_full_search_waits_for_a_peer_only_until_defer_full_s_after_the_map_was_first_seen():
    book = FitBook()
    settings = MergerSettings(period_s=10.0, distributed=True, defer_full_s=30.0)
    assert book.deferred(5, [1, 2], [[], ["own"]], settings, now=100.0) == frozenset({0}) and book.deferring
    three, no_hints = [1, 2, 3], [[], [], []]
    assert book.deferred(5, three, no_hints, settings, now=120.0) == frozenset({0, 1, 2})
    assert book.deferred(5, three, no_hints, settings, now=131.0) == frozenset({2})  # 1 and 2 waited 31 s
    assert book.deferred(5, three, no_hints, settings, now=200.0) == frozenset() and not book.deferring
    assert book.deferred(1, [2, 3], [[], []], settings, now=100.0) == frozenset()  # the lowest id
    # holding only a higher id's map, with a lower id alive: that one searches, we wait
    assert book.deferred(4, [18], [[]], settings, now=100.0, alive=frozenset({1, 18})) == frozenset({0})
    assert book.deferred(4, [18], [[]], settings, now=100.0, alive=frozenset({18, 20})) == frozenset()


# ---------------------------------------------------------------------------- trigger and slot
def test_the_trigger_serves_an_urgent_request_at_once_with_its_reasons():
    trigger = MergeTrigger()
    beats = []
    settings = MergerSettings(period_s=3600, min_gap_s=3600, settle_s=3600)
    assert trigger.request("map of vehicle 2") == 1 and trigger.request("merge-now", urgent=True) == 2
    ticket, urgent, reasons = trigger.wait_due(1e12, 0.0, settings, lambda: beats.append(1), 1.0)
    assert (ticket, urgent, reasons) == (2, True, ["map of vehicle 2", "merge-now"]) and beats
    trigger.complete(ticket)
    assert trigger.wait_completed(2, 0.0)
    assert not trigger.wait_completed(3, 0.0)
    assert trigger.wait_due(0.0, 0.0, settings, lambda: None, 1.0) == (2, False, ["period"])  # period due


def test_the_trigger_holds_unsettled_requests_and_returns_none_once_stopped():
    trigger = MergeTrigger()
    settings = MergerSettings(period_s=3600, min_gap_s=3600, settle_s=3600)
    trigger.request("map of vehicle 2")
    got = []

    def wait():
        got.append(trigger.wait_due(1e12, 0.0, settings, lambda: None, 0.05))

    waiter = threading.Thread(target=wait)
    waiter.start()
    waiter.join(0.3)
    assert waiter.is_alive() and got == []  # settling for an hour
    trigger.stop()
    waiter.join(5)
    assert got == [None] and trigger.stopped and trigger.wait_completed(99, 0.0)


def _requests_while_waiting(trigger: MergeTrigger, settings: MergerSettings, new_map: bool) -> float:
    """Six requests 0.08 s apart (0.4 s) while the trigger is waited on; seconds until it was due."""
    def send():
        for vid in range(2, 8):
            trigger.request(f"map of vehicle {vid}", new_map=new_map)
            time.sleep(0.08)

    sender = threading.Thread(target=send)
    t0 = time.monotonic()
    sender.start()
    time.sleep(0.01)
    ticket, _, _ = trigger.wait_due(1e12, 0.0, settings, lambda: None, 0.05)
    waited = time.monotonic() - t0
    sender.join(5)
    trigger.complete(ticket)
    if trigger.requested > ticket:  # serve what came after it was due
        trigger.complete(trigger.wait_due(1e12, 0.0, settings, lambda: None, 0.05)[0])
    return waited


def test_the_trigger_waits_for_new_vehicles_maps_not_for_updates():
    trigger = MergeTrigger()
    settings = MergerSettings(period_s=3600, min_gap_s=0.2, settle_s=0.1)
    # new maps for 0.4 s, longer than min_gap_s: due settle_s after the last one
    assert 0.4 + 0.1 - 0.02 <= _requests_while_waiting(trigger, settings, new_map=True) < 0.75
    # updates of maps already merged: min_gap_s after the first, as before (nothing new left over)
    assert _requests_while_waiting(trigger, settings, new_map=False) < 0.35


def test_the_trigger_waits_while_maps_are_awaited_and_asks_outside_its_lock():
    trigger = MergeTrigger()
    settings = MergerSettings(period_s=3600, min_gap_s=0.2, settle_s=0.1)
    awaited = [2]

    def still_coming() -> int:
        assert trigger._cv.acquire(blocking=False)  # not held by the waiting thread
        trigger._cv.release()
        return awaited[0]

    def arrive():
        time.sleep(0.5)
        awaited[0] = 0
        trigger.request("map of vehicle 3", new_map=True)

    t0 = time.monotonic()
    trigger.request("map of vehicle 2", new_map=True)
    threading.Thread(target=arrive).start()
    ticket, _, reasons = trigger.wait_due(1e12, 0.0, settings, lambda: None, 0.05, still_coming)
    assert 0.5 + 0.1 - 0.02 <= time.monotonic() - t0 < 0.9
    assert reasons == ["map of vehicle 2", "map of vehicle 3"]
    trigger.complete(ticket)
    awaited[0] = 5  # awaited for ever: the first merge still comes, NEW_MAPS_WAIT caps after the first
    t1 = time.monotonic()
    trigger.request("map of vehicle 4", new_map=True)
    trigger.wait_due(1e12, 0.0, settings, lambda: None, 0.05, still_coming)
    assert 0.6 - 0.02 <= time.monotonic() - t1 < 0.9


def test_a_period_long_past_does_not_cut_short_the_wait_for_first_maps():
    trigger = MergeTrigger()
    settings = MergerSettings(period_s=3600, min_gap_s=0.2, settle_s=0.3)
    t0 = time.monotonic()
    trigger.request("map of vehicle 2", new_map=True)
    trigger.wait_due(0.0, 0.0, settings, lambda: None, 0.05)  # the period was due long ago (a frozen host)
    assert time.monotonic() - t0 >= 0.3 - 0.02


def test_the_global_map_slot_versions_installs_within_the_budget_and_releases_on_clear():
    budget = MemoryBudget(1 << 20, baseline_bytes=0)
    slot = GlobalMapSlot(4, budget)
    assert slot.get() is None and slot.version is None
    grid = OccupancyGrid.empty((20, 20, 10), 0.1)
    assert slot.install(grid) and slot.install(grid.copy())
    assert slot.version == 2 and slot.get()[1].vehicle_id == 4
    assert budget.snapshot()["entries"]["global"] == grid.size
    assert not slot.install(OccupancyGrid.empty((200, 200, 100), 0.1))  # over the budget: kept
    assert slot.version == 2
    slot.clear()
    assert slot.get() is None and "global" not in budget.snapshot()["entries"]


def test_the_daemons_settings_come_from_the_configuration():
    config = build_config(parse_args(["--no-config"]))
    s = MergerSettings.from_config(config)
    assert s.period_s == config.merging.period_s and s.distributed == config.merging.distributed
    assert s.min_gap_s == min(config.merging.period_s, MERGE_MIN_GAP_S)
    assert s.settle_s == min(config.sharing.scan_period_s, MERGE_MIN_GAP_S)
    assert s.limits.max_cells == config.sharing.max_map_cells
    assert s.recheck_growth == config.merging.recheck_growth
    assert s.confirm_before_fusing == config.merging.confirm_before_fusing and s.params is None
    assert s.vouched == config.merging.vouched and s.search_threads == config.merging.search_threads == 2


def test_the_publisher_sends_only_changed_edges_with_increasing_versions_and_survives_a_refusal():
    sent = []
    publisher = ResultPublisher(1)
    publisher.publish([], sent.append)
    publisher.publish([_edge(2, FIT)], sent.append)
    publisher.publish([_edge(2, FIT)], sent.append)
    assert len(sent) == 1 and sent[0].vehicle_id == 1 and [e.b for e in sent[0].edges] == [2]
    publisher.publish([_edge(2, MIRROR)], sent.append)
    assert len(sent) == 2 and sent[1].version > sent[0].version

    def refuse(message):
        raise ValueError("too many edges")

    publisher.publish([_edge(3, FIT)], refuse)  # logged, not raised

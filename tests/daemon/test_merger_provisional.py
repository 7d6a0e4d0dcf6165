"""confirm_before_fusing: a fit newly found by a search is provisional (reported, held out of the
global map, not published) until a recheck on grown maps finds it again or the maps stop growing."""

import threading
import time

import numpy as np
from merger_flip import Feed
from merger_flip import flip_merger as _merger

from coopd.geometry import rotation_angle_deg
from coopd.merging import GlobalMergeResult, MergeResult, merge_all


def _right(t, truth) -> bool:
    return np.linalg.norm(t[:3, 3] - truth[:3, 3]) < 0.3 and \
        rotation_angle_deg(t[:3, :3].T @ truth[:3, :3]) < 3


def _global_is_local(m, feed) -> bool:
    return m.global_map()[0].same_cells(feed.local()[0])


def test_the_early_flip_never_reaches_the_global_map(flip):
    maps, truth, early = flip
    feed = Feed(maps)

    def search(reference, others, params, **kw):
        """The daemons' search on these early maps accepted the 180-degree mirror fit (today's
        ranking refuses it as ambiguous); on the later maps the real merge_all runs."""
        if feed.stage != "early":
            return merge_all(reference, others, params, **kw)
        r = MergeResult(True, early, 10, 0.97, 5000, 100, 0.0, "accepted", 0.5, method="full")
        if not kw["hold"](0, r):
            raise AssertionError("the first fit was fused")
        return GlobalMergeResult(reference.copy(), [r], 1, [0], 1)

    m = _merger(feed, search, confirm_before_fusing=True)
    m.merge_once("early")
    o = m.offsets[2]
    assert o["accepted"] and o["provisional"] and not _right(np.reshape(o["transform"], (4, 4)), truth)
    assert m.status()["provisional"] == [2] and _global_is_local(m, feed)
    feed.set("later")  # grown 1.3x: the recheck finds the true fit, a new one, so provisional again
    m.merge_once("grown")
    o = m.offsets[2]
    assert o["provisional"] and _right(np.reshape(o["transform"], (4, 4)), truth)
    assert _global_is_local(m, feed)
    feed.set("later")  # the maps stopped growing: nothing more will tell, the fit is confirmed
    m.merge_once("settled")
    o = m.offsets[2]
    assert o["accepted"] and not o["provisional"] and m.status()["provisional"] == []
    assert _right(np.reshape(o["transform"], (4, 4)), truth) and not _global_is_local(m, feed)


def _same_fit_fake(transform, calls):
    """merge_all's contract on one map: a full search (or, with hints and no contest, the own hint)
    accepting `transform`; the map is fused unless hold() says otherwise."""

    def fake(reference, others, params, **kw):
        method = "full" if not kw.get("hints") or kw.get("contest") else "hint:own"
        r = MergeResult(True, transform, 10, 0.97, 5000, 100, 0.0, "accepted", 0.5, method=method)
        held = kw["hold"](0, r) if "hold" in kw else False
        calls.append((method, held))
        return GlobalMergeResult(reference, [r], 1, [0], int(method == "full"))

    return fake


def test_the_same_fit_found_again_on_grown_maps_is_confirmed_and_only_then_published(flip):
    maps, truth, _ = flip
    calls, published = [], []
    feed = Feed(maps)
    m = _merger(feed, _same_fit_fake(truth, calls), confirm_before_fusing=True, distributed=True,
                sources={"peer_results": lambda: [], "publish_results": published.append})
    m.merge_once("early")
    assert calls == [("full", True)] and published == []
    feed.set("later")  # grown 1.3x: searched again, the same fit: confirmed
    m.merge_once("grown")
    assert calls[1] == ("full", False) and not m.offsets[2]["provisional"]
    assert [e.b for e in published[0].edges] == [2]


def test_our_own_provisional_transform_alone_confirms_nothing_while_the_maps_grow(flip):
    maps, truth, _ = flip
    calls = []
    feed = Feed(maps)
    m = _merger(feed, _same_fit_fake(truth, calls), confirm_before_fusing=True, recheck_growth=100.0)
    m.merge_once("early")
    feed.set("later")  # grown, but not 100x: the own hint validates, the merge stays provisional
    m.merge_once("growing")
    assert calls == [("full", True), ("hint:own", True)] and m.status()["provisional"] == [2]


def test_off_by_default_every_accepted_fit_is_fused_at_once(flip):
    maps, truth, _ = flip
    calls = []
    feed = Feed(maps)
    m = _merger(feed, _same_fit_fake(truth, calls))
    m.merge_once("early")
    assert calls == [("full", False)] and m.offsets[2]["provisional"] is False


def test_the_merging_thread_merges_again_to_confirm_when_nothing_changes(flip):
    maps, truth, _ = flip
    calls = []
    feed = Feed(maps)
    m = _merger(feed, _same_fit_fake(truth, calls), confirm_before_fusing=True, min_gap_s=0.05,
                sources={"local_version": lambda: feed.version})
    t = threading.Thread(target=m.run, daemon=True)
    t.start()
    try:
        m.request("start")
        deadline = time.monotonic() + 10
        while (m.counters["done"] < 2 or m.status()["provisional"]) and time.monotonic() < deadline:
            time.sleep(0.02)
        time.sleep(1.0)  # 20 times min_gap_s: a merger that went on merging would count more than 2
    finally:
        m.stop()
        t.join(5)
    # the same inputs twice: the second merge sees the maps settled and confirms the fit without
    # searching again (merging is deterministic), fusing the map into the global map
    assert calls == [("full", True)] and m.status()["provisional"] == [] and m.counters["done"] == 2
    assert not m.offsets[2]["provisional"] and not _global_is_local(m, feed)


def test_held_fits_are_confirmed_one_settling_period_later_unless_the_maps_changed(flip):
    """The confirmation is looked for settle_s after the merge that held the fit, not min_gap_s: no
    input changed, so it is confirmed then; with the maps changed meanwhile, the next merge waits for
    min_gap_s as any other (here an hour: none within the test)."""
    maps, truth, _ = flip
    for changes in (False, True):
        calls = []
        feed = Feed(maps)
        m = _merger(feed, _same_fit_fake(truth, calls), confirm_before_fusing=True, min_gap_s=3600,
                    settle_s=0.3, sources={"local_version": lambda f=feed: f.version})
        t = threading.Thread(target=m.run, daemon=True)
        t.start()
        try:
            m.request("start")
            deadline = time.monotonic() + 10
            while m.counters["done"] < 1 and time.monotonic() < deadline:
                time.sleep(0.005)
            if changes:
                feed.version += 1  # our map grew: the fit is not confirmed on these inputs
            while not changes and m.status()["provisional"] and time.monotonic() < deadline:
                time.sleep(0.02)
            time.sleep(1.0)
        finally:
            m.stop()
            t.join(5)
        if changes:
            assert m.counters["done"] == 1 and m.status()["provisional"] == [2]
        else:
            assert m.counters["done"] == 2 and m.status()["provisional"] == [] and calls == [("full", True)]


def test_fits_held_by_a_merge_longer_than_settle_s_on_unchanged_maps_are_confirmed_at_once(flip):
    """The maps settled during the merge itself (no input changed while it ran for longer than
    settle_s): its fits are confirmed right after it, not one settling period later; a map that
    changed during the merge leaves them held."""
    maps, truth, _ = flip
    for changes in (False, True):
        calls, done_at = [], []
        feed = Feed(maps)
        fake = _same_fit_fake(truth, calls)

        def slow(*a, changes=changes, feed=feed, fake=fake, **kw):
            time.sleep(0.6)  # a long search: longer than settle_s
            if changes:
                feed.version += 1  # our map grew while it ran
            return fake(*a, **kw)

        m = _merger(feed, slow, confirm_before_fusing=True, min_gap_s=3600, settle_s=0.5,
                    sources={"local_version": lambda f=feed: f.version})
        def timed(reason="request", done_at=done_at, merge_once=m.merge_once):
            done_at.append(time.monotonic())
            return merge_once(reason)

        m.merge_once = timed
        t = threading.Thread(target=m.run, daemon=True)
        t.start()
        try:
            m.request("start")
            deadline = time.monotonic() + 10
            while len(done_at) < 2 and time.monotonic() < deadline:
                time.sleep(0.005)
            time.sleep(0.7)
        finally:
            m.stop()
            t.join(5)
        if changes:
            assert m.counters["done"] == 1 and m.status()["provisional"] == [2] and len(done_at) == 1
        else:
            assert m.counters["done"] == 2 and m.status()["provisional"] == [] and calls == [("full", True)]
            assert done_at[1] - done_at[0] < 0.6 + 0.3, done_at  # the 0.6 s merge, then at once

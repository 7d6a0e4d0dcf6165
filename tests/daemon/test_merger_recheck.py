"""The Merger searches a merged map again once the pair grew (recheck_growth), its known transform
competing, and leaves out a map whose search found two fits until one wins (contested)."""

import numpy as np
from merger_flip import Feed
from merger_flip import flip_merger as _merger

from coopd.geometry import rotation_angle_deg
from coopd.merging import GlobalMergeResult, MergeResult, merge_all


def _offset(m):
    return np.reshape(m.offsets[2]["transform"], (4, 4))


def test_a_map_merged_on_early_maps_is_searched_again_once_grown_and_ends_on_the_truth(flip):
    maps, truth, _ = flip
    feed = Feed(maps)
    m = _merger(feed, merge_all)
    assert m.merge_once("early")["outcome"] == "done"
    feed.set("later")
    assert maps["later"][0].counts().known + maps["later"][1].counts().known >= \
        1.3 * (maps["early"][0].counts().known + maps["early"][1].counts().known)
    assert m.merge_once("later")["outcome"] == "done"
    assert m.counters["full_registrations"] == 2 and m.offsets[2]["method"] == "full"
    assert m.offsets[2]["accepted"]
    t = _offset(m)
    assert np.linalg.norm(t[:3, 3] - truth[:3, 3]) < 0.3
    assert rotation_angle_deg(t[:3, :3].T @ truth[:3, :3]) < 3


def test_an_ambiguous_search_drops_our_transform_and_only_a_winning_search_brings_it_back(flip):
    maps, _, early = flip
    calls, answers = [], []

    def fake(reference, others, params, **kw):
        calls.append(kw)
        accepted, reason, method = answers.pop(0)
        r = MergeResult(accepted, early, 10, 0.97, 5000, 100, 0.0, reason, 0.5, method=method)
        return GlobalMergeResult(reference, [r], 1, [0], int(method == "full"))

    feed = Feed(maps)
    m = _merger(feed, fake)
    answers += [(True, "accepted", "full"), (True, "accepted", "hint:own")]
    m.merge_once("first")
    feed.set("early")
    m.merge_once("warm")
    assert "contest" not in calls[1] and calls[1]["hints"][0][0].source == "own"
    answers.append((False, "ambiguous: a distinct hypothesis scores 0.970", "full"))
    feed.set("later")  # the pair grew 1.3x: the map is searched again, our transform competing
    m.merge_once("recheck")
    assert calls[2]["contest"] == frozenset({0}) and not m.offsets[2]["accepted"]
    answers.append((False, "ambiguous: still", "full"))
    feed.set("later")
    m.merge_once("contested")  # our own transform is gone: nothing to hint, a plain full search
    assert "hints" not in calls[3] and "contest" not in calls[3]
    answers.append((True, "accepted", "full"))
    feed.set("later")
    m.merge_once("resolved")
    assert m.offsets[2]["accepted"] and m.status()["contested"] == []


def test_once_the_maps_stop_growing_a_transform_decided_on_smaller_maps_is_searched_once_more(flip):
    maps, _, early = flip
    calls = []

    def fake(reference, others, params, **kw):
        calls.append(kw)
        method = "full" if not kw.get("hints") or kw.get("contest") else "hint:own"
        r = MergeResult(True, early, 10, 0.97, 5000, 100, 0.0, "accepted", 0.5, method=method)
        return GlobalMergeResult(reference, [r], 1, [0], int(method == "full"))

    feed = Feed(maps)
    m = _merger(feed, fake, recheck_growth=100.0)  # growth alone never rechecks here
    m.merge_once("early")  # full search on the early maps
    feed.set("later")
    m.merge_once("growing")  # the maps grew: the own hint serves
    assert "contest" not in calls[1] and m.offsets[2]["method"] == "hint:own"
    feed.set("later")
    m.merge_once("settled")  # no growth since the last merge: the flight is over, search once more
    assert calls[2]["contest"] == frozenset({0}) and m.offsets[2]["method"] == "full"
    feed.set("later")
    m.merge_once("after")  # decided on the final maps now: hints again
    assert "contest" not in calls[3] and m.status()["rechecks"] == 1


def test_recheck_growth_none_never_searches_a_merged_map_again(flip):
    maps, _, early = flip
    calls = []

    def fake(reference, others, params, **kw):
        calls.append(kw)
        method = "hint:own" if kw.get("hints") else "full"
        r = MergeResult(True, early, 10, 0.97, 5000, 100, 0.0, "accepted", 0.5, method=method)
        return GlobalMergeResult(reference, [r], 1, [0], int(method == "full"))

    feed = Feed(maps)
    m = _merger(feed, fake, recheck_growth=None)
    for stage in ("early", "later", "later"):  # grown 1.3x, then settled: neither rechecks
        feed.set(stage)
        m.merge_once(stage)
    assert [("contest" in kw) for kw in calls] == [False] * 3 and m.status()["rechecks"] == 0
    assert m.offsets[2]["method"] == "hint:own"

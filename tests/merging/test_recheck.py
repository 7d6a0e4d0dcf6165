"""A transform accepted on small early maps of a near-symmetric building can be the mirror fit; once the
maps grew, the maps it merged are searched again with that transform competing (merge_all contest).

The data are two drones' local maps of one small_house flight (tests/merging/data/small_house_flip):
the drones started 180 degrees apart at mirrored poses, so their first maps fit each other almost
as well with no turn at all, and the daemons accepted that fit. A few seconds later the true fit
wins clearly, but the early fit still passes validation when judged alone, so a hint of it would
have lived on for the whole flight."""

import json
from pathlib import Path

import numpy as np
import pytest

from coopd.geometry import rotation_angle_deg
from coopd.io.cmap import load_cmap
from coopd.merging import Hint, coopd_params, merge_all
from coopd.merging.pair import judge, prepare

DATA = Path(__file__).parent / "data" / "small_house_flip"


@pytest.fixture(scope="module")
def flip():
    info = json.loads((DATA / "truth.json").read_text())
    maps = {name: [load_cmap(DATA / f"{name}_{i}.cmap")[0] for i in (1, 2)] for name in ("early", "later")}
    return maps, np.array(info["truth_1_from_2"]), np.array(info["accepted_early_1_from_2"])


def _close(t, truth, m=0.3, deg=3.0):
    t = np.asarray(t, dtype=np.float64).reshape(4, 4)
    return (np.linalg.norm(t[:3, 3] - truth[:3, 3]) < m
            and rotation_angle_deg(t[:3, :3].T @ truth[:3, :3]) < deg)


def test_the_early_fit_is_the_mirror_and_the_truth_agrees_better_on_the_later_maps(flip):
    maps, truth, early = flip
    assert rotation_angle_deg(early[:3, :3].T @ truth[:3, :3]) > 170  # the mirror, not a small error
    params = coopd_params()
    a, b = (prepare(g, params, lazy=True) for g in maps["later"])
    right, wrong = judge(a, b, truth, params), judge(a, b, early, params)
    assert right.accepted and _close(right.transform, truth)
    assert right.score > wrong.score and right.conflicts * 4 < wrong.conflicts


def test_a_contested_hint_competes_with_the_search_and_the_true_fit_wins(flip):
    maps, truth, early = flip
    res = merge_all(maps["later"][0], [maps["later"][1]], hints=[[Hint(early, "own")]],
                    contest=frozenset({0}))
    r = res.results[0]
    assert r.accepted and r.method == "full" and res.full_registrations == 1, r.reason
    assert _close(r.transform, truth)


def test_a_map_in_contest_is_searched_even_when_its_full_search_is_left_to_a_peer(flip):
    maps, truth, early = flip
    res = merge_all(maps["later"][0], [maps["later"][1]], hints=[[Hint(early, "peer")]],
                    hints_only=frozenset({0}), contest=frozenset({0}))
    assert res.full_registrations == 1 and _close(res.results[0].transform, truth)

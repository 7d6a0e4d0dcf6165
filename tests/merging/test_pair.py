import numpy as np
import pytest

from coopd.geometry import rigid, rotation_angle_deg
from coopd.merging.pair import _cell_steps, close_runner_up, merge_pair, prepare
from coopd.merging.params import coopd_params, thesis_params
from coopd.merging.validation import agreement


def _errors(t, truth):
    return rotation_angle_deg(t[:3, :3].T @ truth[:3, :3]), float(np.linalg.norm(t[:3, 3] - truth[:3, 3]))


def test_merge_pair_recovers_the_transform_of_overlapping_maps(near_pair):
    r = merge_pair(near_pair.a, near_pair.b, coopd_params())
    assert r.accepted, r.reason
    rot, trans = _errors(r.transform, near_pair.a_from_b)
    assert rot < 2.0 and trans < 0.2
    assert r.inliers >= 5 and r.score > 0.93
    assert {"search", "validate", "summarise"} <= set(r.timings)


def test_merge_pair_rejects_maps_that_do_not_overlap(far_pair):
    r = merge_pair(far_pair.a, far_pair.b, coopd_params())
    assert not r.accepted
    assert r.reason != "accepted"


@pytest.mark.slow
@pytest.mark.cpu_bound
def test_thesis_variant_runs_every_stage_and_validation_guards_it(near_pair):
    r = merge_pair(near_pair.a, near_pair.b, thesis_params())
    assert {"preprocess", "fast3d", "filter", "orientation", "describe", "match", "ransac"} <= set(r.timings)
    if r.accepted:  # validation must never let a wrong transform through
        rot, trans = _errors(r.transform, near_pair.a_from_b)
        assert rot < 2.0 and trans < 0.3


def test_merge_pair_refuses_empty_and_featureless_maps_with_a_reason():
    from coopd.grid import OccupancyGrid

    empty = OccupancyGrid.empty((10, 10, 10))
    free = OccupancyGrid(np.full((30, 30, 10), 5, dtype=np.int8), 0.1, (-15, -15, 0))
    for a, b in [(empty, empty), (free, free), (empty, free)]:
        r = merge_pair(a, b, coopd_params())
        assert not r.accepted and r.reason


def test_merge_pair_registers_to_a_fraction_of_a_cell(near_pair):
    """With the sub-cell fit after ICP, b's occupied cells land within a third of a cell (mean) of
    where the true transform puts them."""
    from coopd.geometry import apply

    r = merge_pair(near_pair.a, near_pair.b, coopd_params())
    assert r.accepted, r.reason
    b = near_pair.b
    points = (np.argwhere(b.cells >= 50) + b.offset) * b.resolution
    moved = np.linalg.norm(apply(r.transform, points) - apply(near_pair.a_from_b, points), axis=1).mean()
    print(f"mean displacement {moved:.4f} m, {_errors(r.transform, near_pair.a_from_b)[0]:.3f} deg")
    assert moved <= b.resolution / 3


def test_a_runner_up_is_close_against_the_support_of_what_is_accepted():
    """The margin test: a distinct runner-up within min_margin of the winner's support is close. Given
    the support the winner keeps after its sub-cell fit (the lower of before and after), a fit that
    lost most of it leaves the decision ambiguous."""
    assert close_runner_up(6000.0, 6983.0, 0.15)
    assert not close_runner_up(5109.0, 6983.0, 0.15)
    assert close_runner_up(5109.0, min(6983.0, 110.0), 0.15)
    assert not close_runner_up(-50.0, 110.0, 0.15)


def test_cell_steps_bring_a_fit_stopped_cells_off_back_to_the_best_support(near_pair):
    """ICP between cell centres can stop whole cells off the truth in dense structure; stepping b a
    cell at a time while the support rises brings it back, and leaves a fit already there as it is."""
    params = coopd_params()
    a, b = prepare(near_pair.a, params), prepare(near_pair.b, params)
    truth = near_pair.a_from_b
    off = rigid(None, [0.2, -0.1, 0.0]) @ truth
    stepped = _cell_steps(a, b, off, params)
    assert np.abs(stepped[:3, 3] - truth[:3, 3]).max() < 0.11
    best = agreement(a.summary, b.summary, stepped).support(params.conflict_weight)
    assert best > agreement(a.summary, b.summary, off).support(params.conflict_weight)
    assert _cell_steps(a, b, stepped, params) is stepped

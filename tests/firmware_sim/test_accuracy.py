"""firmware_sim.accuracy on synthetic grids: a wall mapped exactly, shifted, partly, with clutter."""

import math
from types import SimpleNamespace

import numpy as np
import pytest

from firmware_sim.accuracy import (
    MAX_TRACK_POINTS,
    map_accuracy,
    offset_error,
    tracks_in_frame,
    transform_points,
)

RES = 0.1


def truth_wall():
    """A 40x40x20 truth volume (origin at world 0) with one wall at x index 20."""
    gt = np.zeros((40, 40, 20), bool)
    gt[20, 5:35, 2:18] = True
    return gt, np.zeros(3)


def map_of(gt, shift=(0, 0, 0), free_before=True):
    """A map grid (same resolution) holding the truth's occupied cells shifted by `shift` cells,
    the cells around the wall known free (the explored region)."""
    cells = np.full(gt.shape, -1, np.int8)
    if free_before:
        cells[10:25, 5:35, 2:18] = 0
    occ = np.argwhere(gt) + np.array(shift)
    cells[tuple(occ.T)] = 100
    return SimpleNamespace(cells=cells, offset=np.zeros(3, np.int64), resolution=RES)


def identity(p):
    return np.asarray(p)


def test_exact_map_is_perfect():
    gt, origin = truth_wall()
    acc = map_accuracy(map_of(gt), identity, gt, origin)
    assert acc["precision"] == 1.0 and acc["recall"] == 1.0
    assert acc["occupied_cells"] == acc["observed_truth_cells"] == int(gt.sum())


def test_one_cell_shift_fails_strict_but_passes_with_slack():
    gt, origin = truth_wall()
    acc = map_accuracy(map_of(gt, shift=(1, 0, 0)), identity, gt, origin)
    assert acc["precision"] == 0.0 and acc["recall"] == 0.0
    assert acc["precision_tol1"] == 1.0 and acc["recall_tol1"] == 1.0


def test_to_world_is_applied():
    """A map built in a frame 1 m along x from the world: the transform puts it back on the truth."""
    gt, origin = truth_wall()
    shifted = map_of(gt, shift=(-10, 0, 0))
    t = np.eye(4)
    t[0, 3] = 10 * RES
    assert map_accuracy(shifted, transform_points(t), gt, origin)["precision"] == 1.0
    assert map_accuracy(shifted, identity, gt, origin)["precision"] == 0.0


def test_recall_counts_only_the_explored_region():
    """Truth cells no known map cell overlaps are not missed; half the wall mapped free is."""
    gt, origin = truth_wall()
    gt_more = gt.copy()
    gt_more[30, 5:35, 2:18] = True  # a second wall the map never saw (all unknown there)
    m = map_of(gt)
    assert map_accuracy(m, identity, gt_more, origin)["recall"] == 1.0
    m.cells[20, 5:20, 2:18] = 0  # half the wall seen as free: missed
    acc = map_accuracy(m, identity, gt_more, origin)
    assert acc["recall"] == pytest.approx(0.5)
    assert acc["precision"] == 1.0


def test_clutter_lowers_precision():
    gt, origin = truth_wall()
    m = map_of(gt)
    n = int(gt.sum())
    m.cells[10, 5:35, 2:18] = 100  # a phantom wall as large as the true one
    acc = map_accuracy(m, identity, gt, origin)
    assert acc["precision"] == pytest.approx(0.5)
    assert acc["occupied_cells"] == 2 * n


def test_empty_map():
    gt, origin = truth_wall()
    m = map_of(gt)
    m.cells[:] = -1
    acc = map_accuracy(m, identity, gt, origin)
    assert acc["precision"] == 0.0 and acc["recall"] == 0.0 and acc["observed_truth_cells"] == 0


def rigid(yaw_deg, t):
    a = math.radians(yaw_deg)
    m = np.eye(4)
    m[:2, :2] = [[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]]
    m[:3, 3] = t
    return m


def test_offset_error():
    assert offset_error(rigid(30, [1, 2, 0]), rigid(30, [1, 2, 0])) == pytest.approx((0.0, 0.0), abs=1e-6)
    dt, dr = offset_error(rigid(32.5, [1.3, 2, 0.4]), rigid(30, [1, 2, 0]))
    assert dt == pytest.approx(0.5)
    assert dr == pytest.approx(2.5)
    assert offset_error(rigid(179, [0, 0, 0]), rigid(-179, [0, 0, 0]))[1] == pytest.approx(2.0)


def drifting_odometry():
    from firmware_sim.odometry import NoiseConfig, OdometryModel

    noise = NoiseConfig(0.0, 0.0, 0.0, drift_xy_m_s=0.01, drift_z_m_s=0.01, drift_yaw_rad_s=0.002)
    return OdometryModel((3.0, 2.0, 0.0), 0.7, noise, np.random.default_rng(4))


def test_map_frame_in_world_carries_the_drift_at_the_origin_time():
    """A map started at t0 = 60 s: map points (reported at t0, minus the origin) go back to the true
    world points only through the frame drifted as at t0; the drift-free frame misses by the drift."""
    from firmware_sim.accuracy import drift_since, map_frame_in_world
    from firmware_sim.frames import rot_z

    odo = drifting_odometry()
    t0 = 60.0
    body0 = np.array([3.2, 2.1, 0.05])
    origin = odo.estimate(t0, body0, rot_z(0.3), np.zeros(3))[0]
    world_pts = np.array([[5.0, 1.0, 1.2], [1.0, 4.0, 0.3], [3.2, 2.1, 0.05]])
    map_pts = np.array([odo.estimate(t0, p, np.eye(3), np.zeros(3))[0] for p in world_pts]) - origin
    back = transform_points(map_frame_in_world(odo, origin, t0))(map_pts)
    assert np.allclose(back, world_pts, atol=1e-9)
    assert np.allclose(back[2], body0)  # the map origin is where the body was
    naive = transform_points(map_frame_in_world(odo, origin))(map_pts)
    shift, rot = drift_since(odo, 0.0, t0)
    assert shift > 0.1 and rot > 1.0
    assert np.abs(naive - world_pts).max() > 0.1
    frames = map_frame_in_world(odo, origin, t0), map_frame_in_world(odo, origin)
    assert offset_error(*frames)[1] == pytest.approx(rot)


def test_tracks_in_frame_carries_known_tracks_and_names_the_others():
    t = np.arange(5000) / 25.0
    flight = np.c_[t, np.cos(t / 10), np.sin(t / 10), np.full_like(t, 1.5), np.ones_like(t),
                   np.zeros((5000, 3))]
    yaw90 = np.array([[0.0, -1, 0, 2], [1, 0, 0, -1], [0, 0, 1, 0], [0, 0, 0, 1]])
    tracks, left_out = tracks_in_frame({1: flight[:40], 2: flight, 3: flight, 4: np.zeros((0, 8))},
                                       {1: np.eye(4), 2: yaw90, 3: None, 4: np.eye(4)})
    assert left_out == [3] and sorted(tracks) == [1, 2]  # 4 flew nowhere: nothing to draw
    assert np.allclose(tracks[1], flight[:40, 1:3])
    assert len(tracks[2]) == MAX_TRACK_POINTS
    assert np.allclose(tracks[2][0], [2 - flight[0, 2], -1 + flight[0, 1]])  # x' = 2 - y, y' = x - 1
    assert np.allclose(tracks[2][-1], [2 - flight[-1, 2], -1 + flight[-1, 1]])  # the last position kept

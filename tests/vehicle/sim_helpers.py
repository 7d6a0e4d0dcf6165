"""Helpers for tests against firmware_sim: waiting, truth in a vehicle's map frame."""

import time

import numpy as np

from coopd.geometry import quat_to_matrix, rotation_angle_deg
from coopd.vehicle.pose_buffer import PoseBuffer, PoseSample


def wait_until(predicate, timeout: float, poll: float = 0.02) -> bool:
    """Poll predicate until true or timeout (seconds); returns its last value."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(poll)
    return bool(predicate())


def truth_buffer(sim, i: int = 0) -> PoseBuffer:
    """The emulator's logged true trajectory (world frame) as an interpolable buffer."""
    rows = sim.trajectory(i)
    buf = PoseBuffer(capacity=len(rows) + 2, max_gap_s=0.1)
    for r in rows:
        buf.append(PoseSample(float(r[0]), r[1:4].copy(), r[4:8].copy()))
    return buf


def pose_errors(link, sim, i: int = 0):
    """(position error m, attitude error deg) of every buffered map-frame pose vs the truth
    expressed in the vehicle's odometry frame and shifted to the link's map origin."""
    truth = truth_buffer(sim, i)
    odo = sim.vehicle(i).odometry
    span = truth.span()
    pos_err, att_err = [], []
    for s in link.poses.samples():
        if not span[0] <= s.t_fc <= span[1]:
            continue
        t = truth.at(s.t_fc)
        expected = odo.world_to_local_point(t.position) - link.odometry.origin_enu
        pos_err.append(float(np.linalg.norm(s.position - expected)))
        r_expected = odo.frame_rot.T @ quat_to_matrix(t.quaternion)
        att_err.append(rotation_angle_deg(quat_to_matrix(s.quaternion).T @ r_expected))
    return np.array(pos_err), np.array(att_err)


_CORNERS = np.array([[x, y, z] for x in (-0.49, 0.49) for y in (-0.49, 0.49) for z in (-0.49, 0.49)])


def _overlapped_truth_cells(keys, grid_res, to_world, gt_shape, gt_origin, gt_res, chunk=100_000):
    """For each map cell (key), the ground-truth cell indices its 8 (slightly shrunk) corners fall in:
    (n, 8, 3) ints and an (n, 8) in-bounds mask."""
    out_idx, out_ok = [], []
    for lo in range(0, len(keys), chunk):
        k = keys[lo : lo + chunk]
        pts = ((k[:, None, :] + _CORNERS[None]) * grid_res).reshape(-1, 3)
        idx = np.round((to_world(pts) - gt_origin) / gt_res).astype(np.int64).reshape(len(k), 8, 3)
        out_idx.append(idx)
        out_ok.append(np.all((idx >= 0) & (idx < np.array(gt_shape)), axis=2))
    if not out_idx:
        return np.zeros((0, 8, 3), np.int64), np.zeros((0, 8), bool)
    return np.concatenate(out_idx), np.concatenate(out_ok)


def map_accuracy(grid, to_world, gt, gt_origin, gt_res=0.1, threshold=50) -> dict:
    """Occupied-cell precision and recall of a map against a ground-truth voxel grid.

    A map cell and a truth cell match when they overlap in space (the map's cell corners, mapped to
    the world, fall in the truth cell): the two grids are offset and rotated against each other, so
    cell-index equality would be meaningless. Recall counts truth-occupied cells in the observed
    region (overlapped by some known map cell). `*_tol1` repeat both with one cell of slack.
    """
    from scipy import ndimage

    cells = grid.cells
    occ = np.argwhere(cells >= threshold) + grid.offset
    known = np.argwhere(cells >= 0) + grid.offset
    occ_idx, occ_ok = _overlapped_truth_cells(occ, grid.resolution, to_world, gt.shape, gt_origin, gt_res)
    kn_idx, kn_ok = _overlapped_truth_cells(known, grid.resolution, to_world, gt.shape, gt_origin, gt_res)

    def hits(volume, idx, ok):
        v = np.zeros(ok.shape, bool)
        v[ok] = volume[tuple(idx[ok].T)]
        return v.any(axis=1)

    def paint(idx, ok):
        v = np.zeros(gt.shape, bool)
        v[tuple(idx[ok].T)] = True
        return v

    pred_vol, known_vol = paint(occ_idx, occ_ok), paint(kn_idx, kn_ok)
    observed = gt & known_vol
    dil = np.ones((3, 3, 3), bool)
    gt1, pred1 = ndimage.binary_dilation(gt, dil), ndimage.binary_dilation(pred_vol, dil)
    return {
        "occupied_cells": int(len(occ)),
        "observed_truth_cells": int(observed.sum()),
        "precision": float(hits(gt, occ_idx, occ_ok).mean()) if len(occ) else 0.0,
        "recall": float((observed & pred_vol).sum() / max(observed.sum(), 1)),
        "precision_tol1": float(hits(gt1, occ_idx, occ_ok).mean()) if len(occ) else 0.0,
        "recall_tol1": float((observed & pred1).sum() / max(observed.sum(), 1)),
    }

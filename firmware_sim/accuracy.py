"""Accuracy against the world's ground truth: how far a map's occupied cells lie from the true
surfaces, how much of the surfaces it saw it holds, its free space; the strict voxel figures; offset
errors.

Pure functions over numpy arrays; a map is anything with `cells` (int8 log-odds-like values, -1 =
unknown), `offset` (key of cells[0, 0, 0]) and `resolution` (m), as coopd's OccupancyGrid; cell key
k is centred at k * resolution.
"""

from __future__ import annotations

import math

import numpy as np

from coopd.geometry import invert

OCCUPIED = 50
"""Cell value from which a map cell counts as occupied (coopd.grid.OCCUPIED_THRESHOLD)."""

_CORNERS = np.array([[x, y, z] for x in (-0.49, 0.49) for y in (-0.49, 0.49) for z in (-0.49, 0.49)])


def overlapped_truth_cells(keys, grid_res, to_world, gt_shape, gt_origin, gt_res, chunk=100_000):
    """For each map cell (key), the truth cell indices its 8 (slightly shrunk) corners fall in:
    (n, 8, 3) ints and an (n, 8) in-bounds mask."""
    keys = np.asarray(keys).reshape(-1, 3)
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


def map_accuracy(grid, to_world, gt, gt_origin, gt_res=0.1, threshold=OCCUPIED) -> dict:
    """Occupied-cell precision and recall of a map against a ground-truth voxel grid.

    A map cell and a truth cell match when they overlap in space (the map's cell corners, mapped to
    the world by `to_world`, fall in the truth cell): the two grids are offset and rotated against
    each other, so cell-index equality would be meaningless. Recall counts truth-occupied cells in
    the explored region (overlapped by some known map cell). `*_tol1` repeat both with one truth
    cell of slack.
    """
    from scipy import ndimage

    cells = grid.cells
    occ = np.argwhere(cells >= threshold) + grid.offset
    known = np.argwhere(cells >= 0) + grid.offset
    occ_idx, occ_ok = overlapped_truth_cells(occ, grid.resolution, to_world, gt.shape, gt_origin, gt_res)
    kn_idx, kn_ok = overlapped_truth_cells(known, grid.resolution, to_world, gt.shape, gt_origin, gt_res)

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


def surface_distance(points, shapes, chunk: int = 200_000) -> np.ndarray:
    """Distance (m) from each point (n, 3, world frame) to the nearest face of any shape: the
    absolute signed distance of the nearest shape. Faces buried inside another shape (a wall's foot
    on the floor) count as surface too; they lie within a wall's thickness of a real one."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    out = np.full(len(pts), np.inf)
    for lo in range(0, len(pts), chunk):
        p = pts[lo : lo + chunk]
        best = out[lo : lo + chunk]
        for s in shapes:
            np.minimum(best, np.abs(_signed_distance(s, p)), out=best)
    return out


def _signed_distance(shape, p: np.ndarray) -> np.ndarray:
    """Signed distance of points to one Box or vertical Cylinder (negative inside)."""
    c = np.asarray(shape.center, dtype=np.float64)
    if hasattr(shape, "radius"):
        radial = np.linalg.norm(p[:, :2] - c[:2], axis=1) - shape.radius
        q = np.stack([radial, np.abs(p[:, 2] - c[2]) - shape.half_height], axis=1)
    else:
        q = np.abs(p - c) - np.asarray(shape.half, dtype=np.float64)
    return np.linalg.norm(np.maximum(q, 0.0), axis=1) + np.minimum(q.max(axis=1), 0.0)


def occupied_centres(grid, to_world, threshold=OCCUPIED) -> np.ndarray:
    """World coordinates (n, 3) of the centres of a map's occupied cells."""
    keys = np.argwhere(grid.cells >= threshold) + np.asarray(grid.offset)
    return to_world(keys * grid.resolution) if len(keys) else np.zeros((0, 3))


def surface_accuracy(grid, world_from_map, shapes, seen_points, threshold=OCCUPIED) -> dict:
    """Precision and recall of a map (its frame at the 4x4 `world_from_map`) against the true
    surfaces, with one cell of tolerance.

    Precision: distance from each occupied cell's centre to the nearest true surface (mean, p95,
    share within one cell: a perfect voxelisation's centres are within half a cell diagonal).
    Recall: share of `seen_points` (world points on the surfaces the vehicle saw) whose cell in
    the map, or one of its 26 neighbours, is occupied."""
    from scipy import ndimage

    res = float(grid.resolution)
    to_world, to_map = transform_points(world_from_map), transform_points(invert(world_from_map))
    centres = occupied_centres(grid, to_world, threshold)
    seen = np.asarray(seen_points, dtype=np.float64).reshape(-1, 3)
    out = {"occupied_cells": int(len(centres)), "seen_points": int(len(seen)),
           "surface_precision": 0.0, "surface_mean_m": None, "surface_p95_m": None, "surface_recall": 0.0}
    if not len(centres):
        return out
    d = surface_distance(centres, shapes)
    within = res * (1 + 1e-9)   # a centre exactly one cell away counts, rounding aside
    out.update(surface_precision=float(np.mean(d <= within)), surface_mean_m=float(d.mean()),
               surface_p95_m=float(np.percentile(d, 95)))
    if len(seen):
        near = ndimage.binary_dilation(grid.cells >= threshold, np.ones((3, 3, 3), bool))
        out["surface_recall"] = float(np.mean(_cells_at(near, grid, to_map(seen), False)))
    return out


def _cells_at(volume, grid, points_map, outside):
    """volume[cell of each map-frame point], `outside` for points beyond the grid."""
    keys = np.round(points_map / grid.resolution).astype(np.int64) - np.asarray(grid.offset)
    inside = np.all((keys >= 0) & (keys < np.array(volume.shape)), axis=1)
    out = np.full(len(keys), outside, dtype=volume.dtype)
    out[inside] = volume[tuple(keys[inside].T)]
    return out


def free_share(grid, world_from_map, points, threshold=OCCUPIED) -> float:
    """Share of truly free world points (n, 3) that the map (its frame at the 4x4
    `world_from_map`) holds as free: known and under the occupied threshold."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if not len(pts):
        return 0.0
    values = _cells_at(grid.cells, grid, transform_points(invert(world_from_map))(pts), -1)
    return float(np.mean((values >= 0) & (values < threshold)))


def ray_samples(origins, dirs, hit_m, max_range: float, step: float, shapes, clearance: float):
    """Truth samples of what rays saw: the surface points they hit within max range, and free
    points every `step` metres along each ray up to its hit or max range, keeping only those more
    than `clearance` from any surface (so a cell holding one is truly free).

    origins, dirs (n, 3; dirs unit), hit_m (n; distance to the first surface, inf for none)."""
    o, d = np.asarray(origins, np.float64).reshape(-1, 3), np.asarray(dirs, np.float64).reshape(-1, 3)
    h = np.asarray(hit_m, np.float64).reshape(-1)
    seen = h <= max_range
    surface = o[seen] + d[seen] * h[seen, None]
    reach = np.minimum(h, max_range)
    steps = np.arange(step, max_range, step)
    along = steps[None, :] < reach[:, None]
    ray, k = np.nonzero(along)
    free = o[ray] + d[ray] * steps[k, None]
    if len(free):
        free = free[surface_distance(free, shapes) > clearance]
    return surface, free


def transform_points(t: np.ndarray):
    """The function p -> R p + t of a 4x4 rigid transform, for map_accuracy's `to_world`."""
    t = np.asarray(t, dtype=np.float64)
    return lambda p: np.asarray(p, dtype=np.float64) @ t[:3, :3].T + t[:3, 3]


def offset_error(estimated, truth) -> tuple[float, float]:
    """(translation error m, rotation error deg) of an estimated 4x4 rigid transform vs the true one."""
    est, tru = np.asarray(estimated, dtype=np.float64), np.asarray(truth, dtype=np.float64)
    dt = float(np.linalg.norm(est[:3, 3] - tru[:3, 3]))
    c = (np.trace(est[:3, :3].T @ tru[:3, :3]) - 1.0) / 2.0
    return dt, math.degrees(math.acos(min(1.0, max(-1.0, c))))


def map_frame_in_world(odometry, origin_enu, t_origin: float | None = None) -> np.ndarray:
    """4x4 truth of a map frame in the world: the vehicle's reporting frame, as the estimator's drift
    had moved it at t_origin (when the map origin was taken), translated to the origin.

    A map frame set at time t0 inherits the drift accumulated since boot; the drift-free frame
    (t_origin None) is right only for maps started at t = 0."""
    rd, pd = odometry.drift(t_origin) if t_origin is not None else (np.eye(3), np.zeros(3))
    out = np.eye(4)
    out[:3, :3] = odometry.frame_rot @ rd.T
    origin = np.asarray(origin_enu if origin_enu is not None else np.zeros(3), dtype=np.float64)
    out[:3, 3] = odometry.frame_rot @ rd.T @ (origin - pd) + odometry.origin
    return out


def drift_since(odometry, t_origin: float, t_end: float) -> tuple[float, float]:
    """(m, deg) the estimate's frame drifted between the map origin and t_end: the emulator's share
    of a map's error (an accuracy limit, not a bug)."""
    p0 = odometry.drift(t_origin)[1].copy()
    p1 = odometry.drift(t_end)[1]
    turned = odometry.drift_yaw_rate * (odometry.drift_time(t_end) - odometry.drift_time(t_origin))
    return float(np.linalg.norm(p1 - p0)), abs(math.degrees(turned))


MAX_TRACK_POINTS = 2000
"""A drawn track keeps at most this many positions (evenly spaced in time)."""


def tracks_in_frame(trajectories: dict[int, np.ndarray], frame_from_world: dict[int, np.ndarray | None]
                    ) -> tuple[dict[int, np.ndarray], list[int]]:
    """Each vehicle's (N, 2) x/y positions in one map's frame, for a top view: trajectories are
    rows (t, x, y, z, ...) in the world; frame_from_world[vid] carries vehicle vid's positions
    into the map's frame (4x4), or is None when that is not known (then vid is in the second
    list, drawn nowhere). Long tracks are thinned to MAX_TRACK_POINTS, keeping the last position."""
    tracks, left_out = {}, []
    for vid, trajectory in sorted(trajectories.items()):
        transform = frame_from_world.get(vid)
        trajectory = np.asarray(trajectory, dtype=np.float64)
        if transform is None:
            left_out.append(vid)
            continue
        if trajectory.ndim != 2 or len(trajectory) == 0:
            continue
        count = min(len(trajectory), MAX_TRACK_POINTS)
        keep = np.unique(np.linspace(0, len(trajectory) - 1, count).astype(int))
        tracks[vid] = transform_points(transform)(trajectory[keep, 1:4])[:, :2]
    return tracks, left_out

"""Deterministic test scenes: axis-aligned boxes, an analytic depth renderer and ground truth.

The renderer intersects rays with boxes analytically (slab test), so it shares no code with the
mapper's voxel traversal: a traversal bug cannot cancel out in an accuracy test.
"""

from dataclasses import dataclass

import numpy as np

from coopd.geometry import euler_to_matrix, matrix_to_quat
from coopd.mapping import Intrinsics, Pose


@dataclass(frozen=True)
class BoxScene:
    """Solid axis-aligned boxes (n, 2, 3): [min corner, max corner] in metres, map frame."""

    boxes: np.ndarray

    def occupied_keys(self, resolution: float) -> set:
        """Keys of every cell whose cube overlaps a box with positive volume."""
        keys = set()
        for lo, hi in self.boxes:
            klo = np.ceil(lo / resolution - 0.5 + 1e-9).astype(int)
            khi = np.floor(hi / resolution + 0.5 - 1e-9).astype(int)
            xs, ys, zs = (np.arange(klo[a], khi[a] + 1) for a in range(3))
            for x in xs:
                for y in ys:
                    keys.update((int(x), int(y), int(z)) for z in zs)
        return keys


def room_scene(seed: int = 0, size=(8.0, 6.0, 3.0)) -> BoxScene:
    """A closed room (floor, ceiling, four walls) with a few seeded boxes of furniture inside."""
    rng = np.random.default_rng(seed)
    sx, sy, sz = size
    t = 0.2
    boxes = [
        [[-sx / 2, -sy / 2, -t], [sx / 2, sy / 2, 0.0]],            # floor
        [[-sx / 2, -sy / 2, sz], [sx / 2, sy / 2, sz + t]],         # ceiling
        [[-sx / 2 - t, -sy / 2, 0], [-sx / 2, sy / 2, sz]],         # walls
        [[sx / 2, -sy / 2, 0], [sx / 2 + t, sy / 2, sz]],
        [[-sx / 2, -sy / 2 - t, 0], [sx / 2, -sy / 2, sz]],
        [[-sx / 2, sy / 2, 0], [sx / 2, sy / 2 + t, sz]],
    ]
    for _ in range(5):
        w, d, h = rng.uniform(0.4, 1.2), rng.uniform(0.4, 1.2), rng.uniform(0.5, 1.8)
        cx = rng.uniform(-sx / 2 + 0.8, sx / 2 - 0.8)
        cy = rng.uniform(-sy / 2 + 0.8, sy / 2 - 0.8)
        if abs(cx) < 1.2 and abs(cy) < 1.2:      # keep the middle clear for the sensor
            cx += 2.0 * np.sign(cx or 1.0)
        boxes.append([[cx - w / 2, cy - d / 2, 0.0], [cx + w / 2, cy + d / 2, h]])
    return BoxScene(np.array(boxes, dtype=np.float64))


def camera_pose(position, yaw: float, pitch: float = 0.0) -> Pose:
    """Optical-frame pose of a camera at `position` looking along yaw (about z) and pitch (down +)."""
    body = euler_to_matrix(0.0, pitch, yaw)
    optical_in_body = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    return Pose(np.asarray(position, dtype=np.float64), matrix_to_quat(body @ optical_in_body))


def render_depth(scene: BoxScene, intr: Intrinsics, pose: Pose, max_depth: float = 50.0) -> np.ndarray:
    """Float32 depth image (z along the optical axis, metres; 0 where nothing is hit)."""
    sx, sy = intr.ray_slopes()
    dirs_opt = np.stack(np.broadcast_arrays(sx[None, :], sy[:, None], 1.0), axis=-1).reshape(-1, 3)
    dirs = dirs_opt @ pose.rotation().T                      # per unit of optical z
    o = pose.position
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / dirs
    best = np.full(len(dirs), np.inf)
    for lo, hi in scene.boxes:
        t1 = (lo - o) * inv
        t2 = (hi - o) * inv
        t1 = np.where(np.isnan(t1), -np.inf, t1)
        t2 = np.where(np.isnan(t2), np.inf, t2)
        tnear = np.minimum(t1, t2).max(axis=1)
        tfar = np.maximum(t1, t2).min(axis=1)
        ok = (tfar >= tnear) & (tfar > 0)
        t = np.where(tnear > 0, tnear, 0.0)
        best = np.where(ok & (t < best), t, best)
    depth = np.where(np.isfinite(best) & (best <= max_depth), best, 0.0)
    return depth.reshape(intr.height, intr.width).astype(np.float32)


def hit_keys(depth: np.ndarray, intr: Intrinsics, pose: Pose, resolution: float,
             min_range: float, max_range: float) -> set:
    """Keys of the cells holding the true surface points a frame sees within range."""
    sx, sy = intr.ray_slopes()
    z = depth.astype(np.float64)
    pts = np.stack([sx[None, :] * z, sy[:, None] * z, z], axis=-1).reshape(-1, 3)
    zr = z.reshape(-1)
    ok = (zr >= min_range) & (zr <= max_range) & (np.linalg.norm(pts, axis=1) <= max_range)
    world = pts[ok] @ pose.rotation().T + pose.position
    keys = np.floor(world / resolution + 0.5).astype(np.int64)
    return set(map(tuple, keys.tolist()))


def survey_poses(n_stations: int = 4, yaw_steps: int = 12, height: float = 1.2, radius: float = 1.0):
    """Camera poses of a simulated flight: a few stations on a circle, turning on the spot at each,
    looking level and slightly down."""
    poses = []
    for s in range(n_stations):
        a = 2 * np.pi * s / n_stations
        pos = np.array([radius * np.cos(a), radius * np.sin(a), height])
        for k in range(yaw_steps):
            yaw = 2 * np.pi * k / yaw_steps + 0.1 * s
            poses.append(camera_pose(pos, yaw, pitch=0.25 if k % 2 else -0.1))
    return poses


def occupied_accuracy(grid, scene: BoxScene, seen: set, threshold: int = 50) -> dict:
    """Precision of occupied cells vs the scene, recall vs the surface cells actually seen, and the
    fraction of known cells outside every box that the map calls free."""
    truth = scene.occupied_keys(grid.resolution)
    cells = grid.cells
    occ = np.argwhere(cells >= threshold) + grid.offset
    pred = set(map(tuple, occ.tolist()))
    tp = len(pred & truth)
    known = np.argwhere(cells >= 0) + grid.offset
    known_free_truth = [k for k in map(tuple, known.tolist()) if k not in truth]
    free_ok = sum(1 for k in known_free_truth if k not in pred)
    return {
        "precision": tp / max(len(pred), 1),
        "recall": len(pred & seen) / max(len(seen), 1),
        "free_accuracy": free_ok / max(len(known_free_truth), 1),
        "occupied_cells": len(pred),
        "seen_surface_cells": len(seen),
    }

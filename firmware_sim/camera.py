"""Forward pinhole depth camera rendered with mujoco.mj_multiRay (CPU only), encoded as z16."""

from __future__ import annotations

import math
from dataclasses import dataclass

import mujoco
import numpy as np

# Columns are the optical axes (x right, y down, z forward) expressed in body FLU.
BODY_FROM_OPTICAL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


@dataclass(frozen=True)
class CameraConfig:
    """Depth camera settings; extrinsics are the optical centre in body FLU and a downward tilt."""

    width: int = 160
    height: int = 120
    hfov_deg: float = 87.0
    rate_hz: float = 10.0
    min_m: float = 0.2
    max_m: float = 5.0
    scale: float = 0.001
    noise_sigma_m: float = 0.0  # range noise sigma at 1 m; grows with depth squared
    dropout: float = 0.0  # probability that a valid pixel reads 0
    offset_body: tuple[float, float, float] = (0.0, 0.0, 0.0)
    tilt_down_deg: float = 0.0

    def intrinsics(self) -> tuple[float, float, float, float]:
        """(fx, fy, cx, cy) in pixels, square pixels, principal point at the image centre."""
        fx = (self.width / 2.0) / math.tan(math.radians(self.hfov_deg) / 2.0)
        return fx, fx, (self.width - 1) / 2.0, (self.height - 1) / 2.0

    def validate(self) -> None:
        """Raise ValueError on settings the renderer or the wire format cannot honour."""
        if not (1 <= self.width <= 4096 and 1 <= self.height <= 4096):
            raise ValueError("camera resolution must be within 1..4096 per side")
        if not (1.0 <= self.hfov_deg < 179.0) or not (0 < self.rate_hz <= 1000):
            raise ValueError("camera hfov must be in [1, 179) degrees and rate in (0, 1000] Hz")
        if not (0 <= self.min_m < self.max_m) or self.max_m / self.scale > 65535:
            raise ValueError("camera range must satisfy 0 <= min < max <= 65535 * scale")


def optical_rays(cfg: CameraConfig) -> np.ndarray:
    """Ray directions (h*w, 3) in the optical frame, scaled so that each has z = 1 (dist = depth)."""
    fx, fy, cx, cy = cfg.intrinsics()
    u, v = np.meshgrid(np.arange(cfg.width, dtype=float), np.arange(cfg.height, dtype=float))
    return np.stack([(u - cx) / fx, (v - cy) / fy, np.ones_like(u)], axis=-1).reshape(-1, 3)


def body_from_camera(cfg: CameraConfig) -> np.ndarray:
    """Rotation of the optical frame in body FLU including the downward tilt."""
    t = math.radians(cfg.tilt_down_deg)
    ry = np.array([[math.cos(t), 0.0, math.sin(t)], [0.0, 1.0, 0.0], [-math.sin(t), 0.0, math.cos(t)]])
    return ry @ BODY_FROM_OPTICAL


def depth_to_z16(depth: np.ndarray, cfg: CameraConfig) -> np.ndarray:
    """Quantise metres to uint16 units of cfg.scale; out-of-range and no-return pixels become 0."""
    valid = np.isfinite(depth) & (depth >= cfg.min_m) & (depth <= cfg.max_m)
    out = np.zeros(depth.shape, dtype="<u2")
    out[valid] = np.round(depth[valid] / cfg.scale).astype("<u2")
    return out


class DepthCamera:
    """Renders one vehicle's depth image from the current MuJoCo state."""

    def __init__(self, model: mujoco.MjModel, body_id: int, cfg: CameraConfig, rng: np.random.Generator):
        """Precompute the rays in body coordinates and the output buffers."""
        cfg.validate()
        self.model, self.body_id, self.cfg, self.rng = model, body_id, cfg, rng
        self.rays_cam = optical_rays(cfg) @ body_from_camera(cfg).T  # rays in body FLU
        self.n = cfg.width * cfg.height
        self.cutoff = cfg.max_m * float(np.max(np.linalg.norm(self.rays_cam, axis=1))) + 0.01
        self.geomid = np.zeros(self.n, dtype=np.int32)
        self.dist = np.zeros(self.n, dtype=np.float64)
        self.frames = 0
        self.frames_dropped = 0  # render jobs discarded because the render thread fell behind

    def render_depth(self, data: mujoco.MjData) -> np.ndarray:
        """Depth (metres, NaN = no return) as an (h, w) array for the body's current pose."""
        self._cast(data)
        depth = np.where(self.dist >= 0, self.dist, np.nan).reshape(self.cfg.height, self.cfg.width)
        return self._corrupt(depth)

    def _cast(self, data: mujoco.MjData) -> None:
        """One mj_multiRay call: self.dist gets each pixel's depth, -1 where nothing is hit."""
        rot = data.xmat[self.body_id].reshape(3, 3)
        origin = data.xpos[self.body_id] + rot @ np.asarray(self.cfg.offset_body)
        vec = (self.rays_cam @ rot.T).reshape(-1)
        mujoco.mj_multiRay(
            self.model,
            data,
            origin,
            vec,
            None,
            1,
            self.body_id,
            self.geomid,
            self.dist,
            None,
            self.n,
            self.cutoff,
        )

    def _corrupt(self, depth: np.ndarray) -> np.ndarray:
        """Apply the configured range noise and dropouts (seeded)."""
        cfg = self.cfg
        if cfg.noise_sigma_m > 0:
            depth = depth + self.rng.normal(0.0, 1.0, depth.shape) * cfg.noise_sigma_m * depth**2
        if cfg.dropout > 0:
            depth = np.where(self.rng.random(depth.shape) < cfg.dropout, np.nan, depth)
        return depth

    def render_z16(self, data: mujoco.MjData) -> np.ndarray:
        """Render and quantise to the z16 wire encoding."""
        self.frames += 1
        cfg = self.cfg
        if cfg.noise_sigma_m > 0 or cfg.dropout > 0:
            return depth_to_z16(self.render_depth(data), cfg)
        self._cast(data)  # clean fast path: no NaN round trip
        d = self.dist
        valid = (d >= cfg.min_m) & (d <= cfg.max_m)
        out = np.rint(np.where(valid, d, 0.0) / cfg.scale).astype("<u2")
        return out.reshape(cfg.height, cfg.width)

    def header(self, seq: int, t_us: int) -> dict:
        """The camera-protocol header of a frame (see docs/camera-protocol.md)."""
        c = self.cfg
        fx, fy, cx, cy = c.intrinsics()
        return {
            "v": 1,
            "seq": seq,
            "t_us": int(t_us),
            "w": c.width,
            "h": c.height,
            "fx": fx,
            "fy": fy,
            "cx": cx,
            "cy": cy,
            "scale": c.scale,
            "enc": "z16",
            "n": c.width * c.height * 2,
            "min_m": c.min_m,
            "max_m": c.max_m,
        }

"""The depth camera model: pinhole intrinsics, how the camera sits on the body, frame checks."""

from dataclasses import dataclass, field

import numpy as np

from ..geometry import matrix_to_quat, quat_multiply, quat_to_matrix

MAX_PIXELS_PER_SIDE = 8192
FOV_LIMITS_DEG = (10.0, 170.0)
"""Field of view of a plausible depth camera, either axis (RealSense D435: 87 x 58 deg)."""
DEPTH_SCALE_LIMITS = (1e-5, 0.1)
"""Metres per z16 unit of a plausible depth camera (RealSense: 1e-4..1e-3)."""


class FrameRejected(ValueError):
    """A depth frame or pose that cannot be used; the message says why. The grid is untouched."""


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole model of a depth image: pixel (u, v) with depth z sees the optical-frame point
    ((u - cx) / fx * z, (v - cy) / fy * z, z); optical frame x right, y down, z forward."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    depth_scale: float = 0.001
    """Metres per unit of a z16 (uint16) image; ignored for float images, which are metres."""

    def __post_init__(self):
        if not (1 <= self.width <= MAX_PIXELS_PER_SIDE and 1 <= self.height <= MAX_PIXELS_PER_SIDE):
            raise FrameRejected(f"image size {self.width}x{self.height} outside 1..{MAX_PIXELS_PER_SIDE}")
        values = np.array([self.fx, self.fy, self.cx, self.cy, self.depth_scale], dtype=np.float64)
        if not np.all(np.isfinite(values)):
            raise FrameRejected(f"intrinsics not finite: {values}")
        if not (0.1 <= self.fx <= 1e5 and 0.1 <= self.fy <= 1e5):
            raise FrameRejected(f"focal lengths fx={self.fx}, fy={self.fy} outside 0.1..1e5 px")
        if not (-self.width <= self.cx <= 2 * self.width and -self.height <= self.cy <= 2 * self.height):
            raise FrameRejected(f"principal point ({self.cx}, {self.cy}) far outside the image")
        if not (1e-6 <= self.depth_scale <= 1.0):
            raise FrameRejected(f"depth scale {self.depth_scale} m/unit outside 1e-6..1")

    def implausible(self) -> str | None:
        """Why no real depth camera has these intrinsics (None: plausible). Today's hard limits above
        keep the arithmetic finite; these keep a misconfigured driver's frames out of the map: a
        field of view outside FOV_LIMITS_DEG on either axis, the principal point outside the image,
        or a depth scale outside DEPTH_SCALE_LIMITS (z16 then spans under 0.65 m or beyond 6.5 km)."""
        if not (-0.5 <= self.cx <= self.width - 0.5 and -0.5 <= self.cy <= self.height - 0.5):
            return (f"principal point ({self.cx:.6g}, {self.cy:.6g}) px outside the "
                    f"{self.width}x{self.height} image")
        axes = (("horizontal", self.width, self.fx, self.cx), ("vertical", self.height, self.fy, self.cy))
        for axis, n, f, c in axes:
            fov = float(np.degrees(np.arctan((c + 0.5) / f) + np.arctan((n - 0.5 - c) / f)))
            if not FOV_LIMITS_DEG[0] <= fov <= FOV_LIMITS_DEG[1]:
                return (f"{axis} field of view {fov:.3g} deg (focal length {f:.6g} px over {n} px) "
                        f"outside {FOV_LIMITS_DEG[0]:g}..{FOV_LIMITS_DEG[1]:g} deg")
        if not DEPTH_SCALE_LIMITS[0] <= self.depth_scale <= DEPTH_SCALE_LIMITS[1]:
            return (f"depth scale {self.depth_scale:.6g} m/unit outside {DEPTH_SCALE_LIMITS[0]:g}.."
                    f"{DEPTH_SCALE_LIMITS[1]:g} (z16 would span {65535 * self.depth_scale:.6g} m)")
        return None

    @classmethod
    def from_fov(cls, width: int, height: int, hfov_deg: float, depth_scale: float = 0.001) -> "Intrinsics":
        """Square pixels, principal point at the image centre, horizontal field of view given."""
        fx = (width / 2.0) / np.tan(np.radians(hfov_deg) / 2.0)
        return cls(width, height, fx, fx, (width - 1) / 2.0, (height - 1) / 2.0, depth_scale)

    def ray_slopes(self) -> tuple[np.ndarray, np.ndarray]:
        """Per-column x/z and per-row y/z of the optical rays through pixel centres."""
        u = np.arange(self.width, dtype=np.float64)
        v = np.arange(self.height, dtype=np.float64)
        return (u - self.cx) / self.fx, (v - self.cy) / self.fy


# Optical frame (x right, y down, z forward) expressed in the body frame (x forward, y left, z up).
_BODY_FROM_OPTICAL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


@dataclass(frozen=True)
class Pose:
    """Position (metres) and attitude (unit quaternion w, x, y, z) of a frame in the map frame."""

    position: np.ndarray
    quaternion: np.ndarray

    def __post_init__(self):
        p = np.asarray(self.position, dtype=np.float64).reshape(-1)
        q = np.asarray(self.quaternion, dtype=np.float64).reshape(-1)
        if p.shape != (3,) or q.shape != (4,):
            raise FrameRejected("pose needs a 3-vector position and a 4-vector quaternion")
        if not (np.all(np.isfinite(p)) and np.all(np.isfinite(q))):
            raise FrameRejected("pose is not finite")
        n = float(np.linalg.norm(q))
        if abs(n - 1.0) > 0.1:
            raise FrameRejected(f"quaternion norm {n:.3f} is not close to 1")
        object.__setattr__(self, "position", p)
        object.__setattr__(self, "quaternion", q / n)

    def rotation(self) -> np.ndarray:
        return quat_to_matrix(self.quaternion)


@dataclass(frozen=True)
class CameraMount:
    """Where the camera sits on the body: translation (m) and rotation (w, x, y, z) of the
    optical frame relative to a forward-looking camera at the body origin."""

    translation: np.ndarray = field(default_factory=lambda: np.zeros(3))
    rotation: np.ndarray = field(default_factory=lambda: np.array([1.0, 0.0, 0.0, 0.0]))

    def camera_pose(self, body: Pose) -> Pose:
        """Pose of the optical frame in the map frame, given the body pose."""
        r_body = body.rotation()
        position = body.position + r_body @ np.asarray(self.translation, dtype=np.float64)
        r_cam = r_body @ quat_to_matrix(self.rotation) @ _BODY_FROM_OPTICAL
        return Pose(position, matrix_to_quat(r_cam))

    def tilted(self, pitch_down_deg: float) -> "CameraMount":
        """The same mount pitched down by an angle (about the body y axis)."""
        half = np.radians(pitch_down_deg) / 2.0
        q = quat_multiply(self.rotation, [np.cos(half), 0.0, np.sin(half), 0.0])
        return CameraMount(self.translation, q)


def check_depth(depth, intrinsics: Intrinsics) -> np.ndarray:
    """Return the depth image as a C-contiguous uint16 or float32 array, or raise FrameRejected."""
    if not isinstance(depth, np.ndarray):
        raise FrameRejected(f"depth must be a numpy array, got {type(depth).__name__}")
    if depth.shape != (intrinsics.height, intrinsics.width):
        raise FrameRejected(f"depth shape {depth.shape} does not match intrinsics "
                            f"{intrinsics.height}x{intrinsics.width}")
    if depth.dtype == np.uint16 or depth.dtype == np.float32:
        return np.ascontiguousarray(depth)
    if depth.dtype == np.float64:
        return np.ascontiguousarray(depth, dtype=np.float32)
    raise FrameRejected(f"depth dtype {depth.dtype} not supported (uint16 z16 or float metres)")

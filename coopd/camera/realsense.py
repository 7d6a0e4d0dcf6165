"""Intel RealSense depth source via pyrealsense2 (optional extra); frames restamped into FC time."""

from __future__ import annotations

import logging
import threading
import time
from collections import Counter
from collections.abc import Callable

import numpy as np

from ..mapping.sensor import Intrinsics
from .frame import DepthFrame
from .slot import LatestSlot

log = logging.getLogger("coopd.camera")

WAIT_TIMEOUT_MS = 1000


class CameraUnavailable(RuntimeError):
    """The RealSense source cannot run here (module or device missing); the message says what to do."""


def load_pyrealsense2():
    """Import pyrealsense2 or raise CameraUnavailable with the install hint."""
    try:
        import pyrealsense2 as rs
    except ImportError as e:
        raise CameraUnavailable(
            "RealSense source needs the pyrealsense2 module, which is not installed "
            "(pip install 'coopd[realsense]' or pyrealsense2; "
            "or use the camera socket protocol with a driver adapter)"
        ) from e
    return rs


class RealSenseSource:
    """Streams z16 depth from the first (or the given) RealSense device into a LatestSlot.

    Frame times come from the device's global (host-synchronised) clock in wall-clock ms; they are
    turned into our monotonic clock and then into FC time with `local_to_fc` (the vehicle link's
    clock estimate). Frames that arrive before the FC clock is known are dropped and counted.
    """

    def __init__(
        self,
        local_to_fc: Callable[[float], float | None],
        slot: LatestSlot | None = None,
        width: int = 640,
        height: int = 480,
        fps: int = 15,
        serial: str | None = None,
        min_m: float = 0.1,
        max_m: float = 10.0,
    ):
        self.local_to_fc = local_to_fc
        self.slot: LatestSlot[DepthFrame] = slot if slot is not None else LatestSlot()
        self.width, self.height, self.fps, self.serial = width, height, fps, serial
        self.min_m, self.max_m = min_m, max_m
        self.counters: Counter = Counter()
        self._rs = None
        self._pipeline = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._seq = 0

    def open(self) -> None:
        """Find the device and start streaming; raises CameraUnavailable with the reason."""
        rs = load_pyrealsense2()
        devices = rs.context().query_devices()
        serials = [d.get_info(rs.camera_info.serial_number) for d in devices]
        if not serials:
            raise CameraUnavailable("no RealSense device found (check USB connection and udev rules)")
        if self.serial is not None and self.serial not in serials:
            raise CameraUnavailable(f"RealSense {self.serial} not found; present: {', '.join(serials)}")
        cfg = rs.config()
        if self.serial is not None:
            cfg.enable_device(self.serial)
        cfg.enable_stream(rs.stream.depth, self.width, self.height, rs.format.z16, self.fps)
        pipeline = rs.pipeline()
        try:
            profile = pipeline.start(cfg)
        except RuntimeError as e:
            raise CameraUnavailable(f"RealSense refused {self.width}x{self.height}@{self.fps}: {e}") from e
        self._rs, self._pipeline = rs, pipeline
        scale = profile.get_device().first_depth_sensor().get_depth_scale()
        vp = profile.get_stream(rs.stream.depth).as_video_stream_profile().get_intrinsics()
        self.intrinsics = Intrinsics(vp.width, vp.height, vp.fx, vp.fy, vp.ppx, vp.ppy, float(scale))
        problem = self.intrinsics.implausible()
        if problem is not None:
            pipeline.stop()
            raise CameraUnavailable(f"RealSense reports implausible intrinsics: {problem}")
        log.info(
            "RealSense %s streaming %dx%d@%d, %.5f m/unit",
            serials[0] if self.serial is None else self.serial,
            vp.width,
            vp.height,
            self.fps,
            scale,
        )

    def start(self) -> None:
        """open() then read on a thread."""
        self.open()
        self._stop.clear()
        self._thread = threading.Thread(target=self.run, name="coopd-camera", daemon=True)
        self._thread.start()

    def stop(self, timeout: float = 2.0) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout)
            self._thread = None
        if self._pipeline is not None:
            try:
                self._pipeline.stop()
            except RuntimeError:
                pass
            self._pipeline = None

    def run(self) -> None:
        rs = self._rs
        while not self._stop.is_set():
            try:
                frames = self._pipeline.wait_for_frames(WAIT_TIMEOUT_MS)
            except RuntimeError:
                self.counters["timeouts"] += 1
                continue
            depth = frames.get_depth_frame()
            if not depth:
                self.counters["dropped_no_depth"] += 1
                continue
            if depth.get_frame_timestamp_domain() != rs.timestamp_domain.global_time:
                self.counters["dropped_not_global_time"] += 1
                continue
            self.take(np.asanyarray(depth.get_data()), depth.get_timestamp() * 1e-3)

    def take(self, z16: np.ndarray, wall_s: float) -> None:
        """Validate one image stamped in wall-clock seconds and hand it on in FC time."""
        now = time.monotonic()
        local = wall_s - (time.time() - now)
        t_fc = self.local_to_fc(local)
        if t_fc is None:
            self.counters["dropped_no_fc_clock"] += 1
            return
        intr = self.intrinsics
        if z16.dtype != np.uint16 or z16.shape != (intr.height, intr.width):
            self.counters["dropped_bad_image"] += 1
            return
        frame = DepthFrame(self._seq, float(t_fc), z16.copy(), intr, self.min_m, self.max_m, now)
        self._seq += 1
        self.counters["frames"] += 1
        self.slot.put(frame)

"""Intel RealSense depth source via pyrealsense2 (optional extra); frames restamped into FC time."""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import Counter, deque
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from ..mapping.sensor import Intrinsics
from .frame import DepthFrame
from .protocol import MAX_SIDE
from .slot import LatestSlot
from .socket_source import worth_a_line

log = logging.getLogger("coopd.camera")

WAIT_TIMEOUT_MS = 1000
DEVICE_CLOCK_WINDOW = 64
DEVICE_CLOCK_JUMP_S = 1.0


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


def _doc(text: str, default):
    return field(default=default, metadata={"doc": text})


@dataclass(frozen=True)
class RealSenseConfig:
    """[camera.realsense]: stream, range and filters of a RealSense source, and how it recovers."""

    width: int = _doc("depth stream width, pixels (the device must offer width x height at fps)", 640)
    height: int = _doc("depth stream height, pixels", 480)
    fps: int = _doc("depth stream frame rate, frames per second", 15)
    min_m: float = _doc("readings closer than this are no return, metres", 0.1)
    max_m: float = _doc("readings farther than this are no return, metres", 10.0)
    decimation: int = _doc("decimation filter: 1 = off, 2..8 = one pixel per n x n block", 1)
    threshold_filter: bool = _doc("zero readings outside min_m..max_m in librealsense, before coopd", True)
    reopen_after_s: float = _doc("no frame for this long: close and reopen the device (unplugged)", 3.0)
    retry_max_s: float = _doc("longest wait between attempts to open a missing device, seconds", 10.0)

    def __post_init__(self):
        for name, lo, hi in (("width", 1, MAX_SIDE), ("height", 1, MAX_SIDE), ("fps", 1, 300),
                             ("decimation", 1, 8)):
            v = getattr(self, name)
            if type(v) is not int or not lo <= v <= hi:
                raise ValueError(f"{name} {v!r} is outside {lo}..{hi}")
        lo, hi = self.min_m, self.max_m  # one key named per message: the config error points at it
        if not (math.isfinite(lo) and 0.0 <= lo < 65.0):
            raise ValueError(f"min_m {lo} is outside 0..65 m")
        if not (math.isfinite(hi) and lo < hi <= 65.0):
            raise ValueError(f"max_m {hi} must be above the near end of the range ({lo} m) and at most 65 m")
        if not 0.5 <= self.reopen_after_s <= 60.0:
            raise ValueError(f"reopen_after_s {self.reopen_after_s} is outside 0.5..60 s")
        if not 0.5 <= self.retry_max_s <= 300.0:
            raise ValueError(f"retry_max_s {self.retry_max_s} is outside 0.5..300 s")


class DeviceClock:
    """Maps a device's own clock (RealSense hardware_clock, ms since an arbitrary origin) onto our
    monotonic clock: offset = the smallest (arrival - device stamp) of the recent frames, i.e. the
    frame that reached us fastest. A jump of the device clock (reset, wrap) restarts the window."""

    def __init__(self, window: int = DEVICE_CLOCK_WINDOW):
        self._offsets: deque[float] = deque(maxlen=window)
        self.resets = 0

    def to_local(self, device_s: float, arrival_local_s: float) -> float:
        offset = arrival_local_s - device_s
        if self._offsets and abs(offset - min(self._offsets)) > DEVICE_CLOCK_JUMP_S:
            self._offsets.clear()
            self.resets += 1
        self._offsets.append(offset)
        return device_s + min(self._offsets)


def timestamp_domain_name(domain) -> str:
    """'global_time', 'system_time' or 'hardware_clock' from a pyrealsense2 timestamp_domain value."""
    return getattr(domain, "name", None) or str(domain).rpartition(".")[2]


def host_monotonic_stamp(domain: str, stamp_ms: float, arrival_local_s: float, wall_minus_local_s: float,
                         device_clock: DeviceClock) -> float:
    """A RealSense frame stamp (ms in `domain`) in our monotonic clock, seconds. global_time and
    system_time are host wall-clock ms (global_time: the device clock mapped onto it by
    librealsense; system_time: when the frame reached the host); hardware_clock is the device's."""
    if domain == "hardware_clock":
        return device_clock.to_local(stamp_ms * 1e-3, arrival_local_s)
    return stamp_ms * 1e-3 - wall_minus_local_s


class RealSenseSource:
    """Streams z16 depth from the first (or the given) RealSense device into a LatestSlot.

    Frame stamps (in whichever timestamp domain the device delivers) are turned into our monotonic
    clock and then into FC time with `local_to_fc` (the vehicle link's clock fit), the path
    host-monotonic frames of the socket protocol take. Frames that arrive before the FC clock is
    known are dropped and counted. A device missing at start, or lost later (no frame for
    reopen_after_s), is opened again with backoff up to retry_max_s until stop().
    """

    def __init__(
        self,
        local_to_fc: Callable[[float], float | None],
        slot: LatestSlot | None = None,
        config: RealSenseConfig | None = None,
        serial: str | None = None,
    ):
        self.local_to_fc = local_to_fc
        self.slot: LatestSlot[DepthFrame] = slot if slot is not None else LatestSlot()
        self.config = config if config is not None else RealSenseConfig()
        self.serial = serial
        self.counters: Counter = Counter()
        self.intrinsics: Intrinsics | None = None
        self.last_frame_local: float | None = None
        self.native_id: int | None = None
        self._rs = None
        self._pipeline = None
        self._filters: list = []
        self._device_clock = DeviceClock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._running = False  # run() is reading on some thread: it closes the device when it ends
        self._seq = 0

    @property
    def address(self) -> str:
        return "realsense" if self.serial is None else f"realsense:{self.serial}"

    # -- opening --------------------------------------------------------------------------------

    def open(self) -> None:
        """Find the device and start streaming; raises CameraUnavailable with the reason."""
        rs = load_pyrealsense2()
        c = self.config
        try:
            devices = rs.context().query_devices()
            serials = [d.get_info(rs.camera_info.serial_number) for d in devices]
        except RuntimeError as e:
            raise CameraUnavailable(f"cannot list RealSense devices: {e}") from e
        if not serials:
            raise CameraUnavailable("no RealSense device found (check USB connection and udev rules)")
        if self.serial is not None and self.serial not in serials:
            raise CameraUnavailable(f"RealSense {self.serial} not found; present: {', '.join(serials)}")
        cfg = rs.config()
        if self.serial is not None:
            cfg.enable_device(self.serial)
        cfg.enable_stream(rs.stream.depth, c.width, c.height, rs.format.z16, c.fps)
        pipeline = rs.pipeline()
        try:
            profile = pipeline.start(cfg)
        except RuntimeError as e:
            raise CameraUnavailable(f"RealSense refused {c.width}x{c.height}@{c.fps}: {e}") from e
        try:
            scale = float(profile.get_device().first_depth_sensor().get_depth_scale())
            self._filters = self._make_filters(rs)
        except RuntimeError as e:
            pipeline.stop()
            raise CameraUnavailable(f"RealSense setup failed: {e}") from e
        self._rs, self._pipeline, self._scale = rs, pipeline, scale
        self.intrinsics = None  # taken from the first (filtered) frame: decimation changes them
        vp = profile.get_stream(rs.stream.depth).as_video_stream_profile().get_intrinsics()
        problem = self._intrinsics_of(vp).implausible()
        if problem is not None:
            self.close()
            raise CameraUnavailable(f"RealSense reports implausible intrinsics: {problem}")
        self._device_clock = DeviceClock()
        log.info(
            "RealSense %s streaming %dx%d@%d, %.5f m/unit, range %.2f-%.2f m, decimation %d, threshold %s",
            serials[0] if self.serial is None else self.serial,
            vp.width, vp.height, c.fps, scale, c.min_m, c.max_m, c.decimation,
            "on" if c.threshold_filter else "off",
        )

    def _make_filters(self, rs) -> list:
        c, filters = self.config, []
        if c.decimation > 1:
            dec = rs.decimation_filter()
            dec.set_option(rs.option.filter_magnitude, float(c.decimation))
            filters.append(dec)
        if c.threshold_filter:
            filters.append(rs.threshold_filter(c.min_m, c.max_m))
        return filters

    def _intrinsics_of(self, vp) -> Intrinsics:
        return Intrinsics(vp.width, vp.height, vp.fx, vp.fy, vp.ppx, vp.ppy, self._scale)

    def close(self) -> None:
        if self._pipeline is not None:
            try:
                self._pipeline.stop()
            except RuntimeError:
                pass
            self._pipeline = None

    # -- lifecycle ------------------------------------------------------------------------------

    def start(self) -> None:
        """Check that pyrealsense2 is there (CameraUnavailable if not), then open and read on a thread."""
        load_pyrealsense2()
        self._stop.clear()
        self._thread = threading.Thread(target=self.run, name="coopd-camera", daemon=True)
        self._thread.start()

    def stop(self, timeout: float = 2.0) -> None:
        """Stop reading; the reading thread (ours or the caller's running run()) closes the device."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout)
            self._thread = None
        if not self._running:
            self.close()

    def run(self) -> None:
        """Open (retrying with backoff while the device is missing), read until it is lost, repeat."""
        self._running = True
        try:
            self._open_and_read()
        finally:
            self.close()
            self._running = False

    def _open_and_read(self) -> None:
        self.native_id = threading.get_native_id()
        backoff, failed_since = 0.5, None
        while not self._stop.is_set():
            if self._pipeline is None:
                try:
                    self.open()
                except CameraUnavailable as e:
                    self.counters["open_failures"] += 1
                    if failed_since is None:
                        failed_since, streak = time.monotonic(), 0
                    streak += 1
                    if worth_a_line(streak):
                        log.warning("camera %s: %s; retrying with backoff up to %.0f s (attempt %d)",
                                    self.address, e, self.config.retry_max_s, streak)
                    self._stop.wait(backoff)
                    backoff = min(backoff * 2, self.config.retry_max_s)
                    continue
                except Exception:  # a pyrealsense2 surprise must not kill the thread: count, retry
                    self.counters["internal_errors"] += 1
                    if self.counters["internal_errors"] <= 3:
                        log.exception("camera %s: unexpected error while opening", self.address)
                    self._stop.wait(self.config.retry_max_s)
                    continue
                self.counters["connects"] += 1
                if failed_since is not None:
                    log.info("camera %s open after %d failed attempts in %.1f s",
                             self.address, streak, time.monotonic() - failed_since)
                backoff, failed_since = 0.5, None
            self._read_until_lost()

    def _read_until_lost(self) -> None:
        """Read frames until stop() or no frame for reopen_after_s (then close, for run() to reopen)."""
        last = time.monotonic()
        while not self._stop.is_set():
            try:
                frames = self._pipeline.wait_for_frames(WAIT_TIMEOUT_MS)
            except RuntimeError:
                self.counters["timeouts"] += 1
                silent = time.monotonic() - last
                if silent >= self.config.reopen_after_s:
                    self.counters["disconnect_stall"] += 1
                    log.warning("camera %s: no frame for %.1f s (unplugged?): reopening (reopen #%d)",
                                self.address, silent, self.counters["disconnect_stall"])
                    self.close()
                    return
                continue
            last = time.monotonic()
            try:
                self._process(frames, last)
            except RuntimeError as e:  # librealsense errors on a frame: count it, keep streaming
                self.counters["dropped_frame_errors"] += 1
                if worth_a_line(self.counters["dropped_frame_errors"]):
                    log.warning("camera %s: frame dropped: %s (%d so far)", self.address, e,
                                self.counters["dropped_frame_errors"])

    def _process(self, frames, arrival: float) -> None:
        depth = frames.get_depth_frame()
        if not depth:
            self.counters["dropped_no_depth"] += 1
            return
        domain = timestamp_domain_name(depth.get_frame_timestamp_domain())
        stamp_ms = float(depth.get_timestamp())
        for f in self._filters:
            depth = f.process(depth)
        depth = depth.as_depth_frame()
        vp = depth.get_profile().as_video_stream_profile().get_intrinsics()
        intr = self.intrinsics
        if intr is None or (intr.width, intr.height) != (vp.width, vp.height):
            self.intrinsics = self._intrinsics_of(vp)
        local = host_monotonic_stamp(domain, stamp_ms, arrival, time.time() - time.monotonic(),
                                     self._device_clock)
        self.counters["frames_" + domain] += 1
        self.take(np.asanyarray(depth.get_data()), local, self.intrinsics)

    def take(self, z16: np.ndarray, local_s: float, intrinsics: Intrinsics) -> None:
        """Validate one image stamped in our monotonic clock (seconds) and hand it on in FC time."""
        now = time.monotonic()
        t_fc = self.local_to_fc(local_s)
        if t_fc is None:
            self.counters["dropped_no_fc_clock"] += 1
            return
        if z16.dtype != np.uint16 or z16.shape != (intrinsics.height, intrinsics.width):
            self.counters["dropped_bad_image"] += 1
            return
        c = self.config
        frame = DepthFrame(self._seq, float(t_fc), z16.copy(), intrinsics, c.min_m, c.max_m, now)
        self._seq += 1
        self.counters["frames"] += 1
        self.last_frame_local = now
        self.slot.put(frame)

    def status(self) -> dict:
        """Snapshot for status reports (the same keys as the socket source's)."""
        age = None if self.last_frame_local is None else round(time.monotonic() - self.last_frame_local, 3)
        c = dict(self.counters)
        c["slot_dropped"] = self.slot.dropped
        c["device_clock_resets"] = self._device_clock.resets
        return {
            "address": self.address,
            "connected": self._pipeline is not None,
            "last_frame_age_s": age,
            "thread_native_id": self.native_id,
            "counters": c,
        }

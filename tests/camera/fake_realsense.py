"""A stand-in `pyrealsense2` module with the calls RealSenseSource makes: devices that can be
plugged and unplugged, a depth stream in a chosen timestamp domain, decimation and threshold
filters that behave like librealsense's (pixel blocks, intrinsics scaled; zero outside a range)."""

import threading
import time
import types

import numpy as np

ns = types.SimpleNamespace
DEPTH_SCALE = 0.001
HARDWARE_CLOCK_ORIGIN_S = 5000.0  # the device's clock: our monotonic clock + this
TRANSFER_LATENCY_S = 0.004  # from exposure to arrival on the host


class Domain:
    def __init__(self, name):
        self.name = name


class VideoIntrinsics:
    def __init__(self, width, height, fx, fy, ppx, ppy):
        self.width, self.height, self.fx, self.fy, self.ppx, self.ppy = width, height, fx, fy, ppx, ppy


class DepthFrame:
    def __init__(self, data, intrinsics, domain, stamp_ms):
        self.data, self.intrinsics, self.domain, self.stamp_ms = data, intrinsics, domain, stamp_ms

    def __bool__(self):
        return True

    def get_frame_timestamp_domain(self):
        return Domain(self.domain)

    def get_timestamp(self):
        return self.stamp_ms

    def as_depth_frame(self):
        return self

    def get_profile(self):
        return ns(as_video_stream_profile=lambda: ns(get_intrinsics=lambda: self.intrinsics))

    def get_data(self):
        return self.data


class FakeRealSense:
    """Build with .module(); the test changes .serials (plugging), .domain, .image_m at will."""

    def __init__(self, serials=("123",), domain="global_time", fx=380.0, period_s=0.02):
        self.serials = list(serials)
        self.domain = domain
        self.fx = fx
        self.period_s = period_s
        self.modes: list[tuple] = []  # (width, height, fps) of every pipeline start
        self.decimation: list[float] = []
        self.thresholds: list[tuple[float, float]] = []
        self.image_m = None  # metres per pixel row pattern; None: 2.0 m everywhere
        self.lock = threading.Lock()

    def module(self):
        rs = types.ModuleType("pyrealsense2")
        rs.camera_info = ns(serial_number="serial_number")
        rs.stream = ns(depth="depth")
        rs.format = ns(z16="z16")
        rs.option = ns(filter_magnitude="filter_magnitude")
        rs.context = lambda: ns(query_devices=self._devices)
        rs.config = self._config
        rs.pipeline = self._pipeline
        rs.decimation_filter = self._decimation_filter
        rs.threshold_filter = self._threshold_filter
        return rs

    def _devices(self):
        return [ns(get_info=lambda _k, s=s: s) for s in list(self.serials)]

    def _config(self):
        cfg = ns(stream=None, device=None)
        cfg.enable_stream = lambda _s, w, h, _f, fps: setattr(cfg, "stream", (w, h, fps))
        cfg.enable_device = lambda serial: setattr(cfg, "device", serial)
        return cfg

    def _pipeline(self):
        state = {"running": False, "mode": None, "serial": None}

        def start(cfg):
            if not self.serials or (cfg.device is not None and cfg.device not in self.serials):
                raise RuntimeError("No device connected")
            w, h, fps = cfg.stream
            self.modes.append(cfg.stream)
            state.update(running=True, mode=(w, h, fps), serial=cfg.device or self.serials[0])
            intr = self._intrinsics(w, h)
            return ns(
                get_device=lambda: ns(first_depth_sensor=lambda: ns(get_depth_scale=lambda: DEPTH_SCALE)),
                get_stream=lambda _s: ns(as_video_stream_profile=lambda: ns(get_intrinsics=lambda: intr)),
            )

        def stop():
            if not state["running"]:
                raise RuntimeError("stop() cannot be called before start()")
            state["running"] = False

        def wait_for_frames(timeout_ms):
            time.sleep(self.period_s)
            if not state["running"] or state["serial"] not in self.serials:
                raise RuntimeError(f"Frame didn't arrive within {timeout_ms}")
            w, h, _ = state["mode"]
            return ns(get_depth_frame=lambda: self._frame(w, h))

        return ns(start=start, stop=stop, wait_for_frames=wait_for_frames)

    def _intrinsics(self, w, h):
        return VideoIntrinsics(w, h, self.fx * w / 640, self.fx * w / 640, (w - 1) / 2, (h - 1) / 2)

    def _frame(self, w, h):
        exposure = time.monotonic() - TRANSFER_LATENCY_S
        if self.domain == "hardware_clock":
            stamp_ms = (exposure + HARDWARE_CLOCK_ORIGIN_S) * 1e3
        elif self.domain == "system_time":
            stamp_ms = time.time() * 1e3  # arrival on the host, wall clock
        else:
            stamp_ms = (time.time() - TRANSFER_LATENCY_S) * 1e3
        metres = np.full((h, w), 2.0) if self.image_m is None else np.resize(self.image_m, (h, w))
        data = np.round(metres / DEPTH_SCALE).astype(np.uint16)
        return DepthFrame(data, self._intrinsics(w, h), self.domain, stamp_ms)

    def _decimation_filter(self):
        magnitude = {"n": 1}

        def set_option(_opt, value):
            magnitude["n"] = int(value)
            self.decimation.append(value)

        def process(frame):
            n = magnitude["n"]
            i = frame.intrinsics
            w, h = i.width // n, i.height // n
            intr = VideoIntrinsics(w, h, i.fx / n, i.fy / n, (i.ppx + 0.5) / n - 0.5, (i.ppy + 0.5) / n - 0.5)
            data = np.ascontiguousarray(frame.data[: h * n : n, : w * n : n])
            return DepthFrame(data, intr, frame.domain, frame.stamp_ms)

        return ns(set_option=set_option, process=process)

    def _threshold_filter(self, min_m, max_m):
        self.thresholds.append((min_m, max_m))

        def process(frame):
            metres = frame.data * DEPTH_SCALE
            data = np.where((metres >= min_m) & (metres <= max_m), frame.data, 0).astype(np.uint16)
            return DepthFrame(data, frame.intrinsics, frame.domain, frame.stamp_ms)

        return ns(process=process)

"""RealSense source: clear errors without the module or a device; restamping into FC time."""

import sys
import types

import numpy as np
import pytest

from coopd.camera import CameraUnavailable, RealSenseSource, load_pyrealsense2
from coopd.mapping import Intrinsics


def test_missing_module_gives_a_clear_error(monkeypatch):
    monkeypatch.setitem(sys.modules, "pyrealsense2", None)  # import fails as if not installed
    with pytest.raises(CameraUnavailable, match="pyrealsense2"):
        load_pyrealsense2()
    with pytest.raises(CameraUnavailable, match="not installed"):
        RealSenseSource(lambda t: t).start()


def test_no_device_gives_a_clear_error(monkeypatch):
    fake = types.ModuleType("pyrealsense2")
    fake.context = lambda: types.SimpleNamespace(query_devices=lambda: [])
    monkeypatch.setitem(sys.modules, "pyrealsense2", fake)
    with pytest.raises(CameraUnavailable, match="no RealSense device"):
        RealSenseSource(lambda t: t).open()


def test_frames_are_restamped_into_fc_time_and_checked():
    src = RealSenseSource(lambda local: None)
    src.intrinsics = Intrinsics.from_fov(4, 3, 87.0)
    img = np.arange(12, dtype=np.uint16).reshape(3, 4)
    src.take(img, 1000.0)
    assert src.counters["dropped_no_fc_clock"] == 1 and src.slot.take() is None
    src.local_to_fc = lambda local: local + 50.0
    import time

    wall = time.time()
    src.take(img, wall)
    f = src.slot.take()
    assert f is not None and abs(f.t_fc - (time.monotonic() + 50.0)) < 0.05 and np.array_equal(f.depth, img)
    src.take(img.astype(np.float32), wall)
    src.take(np.zeros((2, 2), np.uint16), wall)
    assert src.counters["dropped_bad_image"] == 2 and src.counters["frames"] == 1


def test_a_device_reporting_implausible_intrinsics_is_refused_at_open(monkeypatch):
    """A device (or a driver bug) reporting a 0.5 px focal length: open() refuses it with the reason."""
    ns = types.SimpleNamespace
    stopped = []
    video = ns(width=640, height=480, fx=0.5, fy=0.5, ppx=319.5, ppy=239.5)
    profile = ns(
        get_device=lambda: ns(first_depth_sensor=lambda: ns(get_depth_scale=lambda: 0.001)),
        get_stream=lambda _s: ns(as_video_stream_profile=lambda: ns(get_intrinsics=lambda: video)),
    )
    fake = types.ModuleType("pyrealsense2")
    fake.camera_info = ns(serial_number="serial")
    fake.stream = ns(depth="depth")
    fake.format = ns(z16="z16")
    fake.context = lambda: ns(query_devices=lambda: [ns(get_info=lambda _k: "123")])
    fake.config = lambda: ns(enable_stream=lambda *a: None, enable_device=lambda s: None)
    fake.pipeline = lambda: ns(start=lambda cfg: profile, stop=lambda: stopped.append(True))
    monkeypatch.setitem(sys.modules, "pyrealsense2", fake)
    with pytest.raises(CameraUnavailable, match="implausible intrinsics: horizontal field of view 180 deg"):
        RealSenseSource(lambda t: t).open()
    assert stopped == [True]

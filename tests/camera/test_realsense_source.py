"""RealSense source: clear errors without the module or a device; restamping into FC time."""

import sys
import time
import types

import numpy as np
import pytest
from fake_driver import take_frames, wait_until
from fake_realsense import FakeRealSense

from coopd.camera import CameraUnavailable, RealSenseConfig, RealSenseSource, load_pyrealsense2
from coopd.daemon.config import ConfigError, parse_config
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
    intr = Intrinsics.from_fov(4, 3, 87.0)
    img = np.arange(12, dtype=np.uint16).reshape(3, 4)
    src.take(img, time.monotonic(), intr)
    assert src.counters["dropped_no_fc_clock"] == 1 and src.slot.take() is None
    src.local_to_fc = lambda local: local + 50.0
    local = time.monotonic()
    src.take(img, local, intr)
    f = src.slot.take()
    assert f is not None and f.t_fc == pytest.approx(local + 50.0) and np.array_equal(f.depth, img)
    src.take(img.astype(np.float32), local, intr)
    src.take(np.zeros((2, 2), np.uint16), local, intr)
    assert src.counters["dropped_bad_image"] == 2 and src.counters["frames"] == 1


@pytest.fixture
def realsense(monkeypatch):
    fake = FakeRealSense()
    monkeypatch.setitem(sys.modules, "pyrealsense2", fake.module())
    return fake


@pytest.fixture
def running():
    """Start a RealSenseSource (stopped after the test)."""
    started = []

    def start(config=None, offset_s=100.0, serial=None):
        src = RealSenseSource(lambda local: local + offset_s, config=config, serial=serial)
        started.append(src)
        src.start()
        return src

    yield start
    for src in started:
        src.stop()


def test_a_device_reporting_implausible_intrinsics_is_refused_at_open(realsense):
    """A device (or a driver bug) reporting a 0.5 px focal length: open() refuses it with the reason."""
    realsense.fx = 0.5
    src = RealSenseSource(lambda t: t)
    with pytest.raises(CameraUnavailable, match="implausible intrinsics: horizontal field of view 180 deg"):
        src.open()
    assert src.status()["connected"] is False  # the pipeline was stopped again


def test_stream_size_rate_range_and_filters_come_from_the_config(realsense, running):
    """848x480@30 with decimation 2 and a 0.3-4 m threshold: half-size frames with halved focal
    lengths, readings outside the range zeroed; the configured range travels with each frame."""
    realsense.image_m = np.array([0.2, 1.0, 2.5, 5.0])  # repeated along each row
    cfg = RealSenseConfig(width=848, height=480, fps=30, decimation=2, min_m=0.3, max_m=4.0)
    src = running(cfg)
    frames = take_frames(src, 3, 5.0)
    assert len(frames) == 3, src.status()
    assert realsense.modes == [(848, 480, 30)] and realsense.decimation == [2.0]
    assert realsense.thresholds == [(0.3, 4.0)]
    f = frames[-1]
    assert f.depth.shape == (240, 424) and f.intrinsics.fx == pytest.approx(380.0 * 848 / 640 / 2)
    assert (f.intrinsics.width, f.intrinsics.height) == (424, 240) and (f.min_m, f.max_m) == (0.3, 4.0)
    # decimation keeps every other column: 0.2, 2.5, 0.2, 2.5 ... (row pattern 0.2 1.0 2.5 5.0, resized)
    kept = sorted(set(np.unique(f.depth).tolist()))
    assert kept == [0, 1000, 2500] or kept == [0, 2500] or kept == [0, 1000], kept
    assert not np.any(f.depth == 200) and not np.any(f.depth == 5000)  # outside 0.3..4 m: zeroed


def test_without_filters_the_stream_is_passed_through(realsense, running):
    realsense.image_m = np.array([0.2, 5.0])
    src = running(RealSenseConfig(threshold_filter=False))
    frames = take_frames(src, 2, 5.0)
    assert len(frames) == 2 and realsense.thresholds == [] and realsense.decimation == []
    assert frames[-1].depth.shape == (480, 640) and set(np.unique(frames[-1].depth)) == {200, 5000}


@pytest.mark.parametrize("domain", ["global_time", "system_time", "hardware_clock"])
def test_every_timestamp_domain_is_converted_into_fc_time(realsense, running, domain):
    """Before, every frame outside global_time was dropped. Each domain now lands in FC time (here
    our monotonic clock + 100 s) at its exposure (system_time: its arrival), before it is handed on;
    a wrong conversion would be off by the clock origins (5000 s device, 1.7e9 s wall clock)."""
    realsense.domain = domain
    src = running()
    frames = take_frames(src, 8, 5.0)
    assert len(frames) == 8 and src.counters["frames_" + domain] >= 8, src.status()
    lag = [f.received_local + 100.0 - f.t_fc for f in frames]
    print(domain, "received - stamp, ms:", [round(x * 1e3, 1) for x in lag])
    assert all(0.0 <= x < 0.25 for x in lag), lag  # the processing time on a loaded machine


def test_an_unplugged_camera_is_reopened_when_it_comes_back(realsense, running, caplog):
    caplog.set_level("INFO", logger="coopd.camera")
    src = running(RealSenseConfig(reopen_after_s=0.5, retry_max_s=1.0))
    assert len(take_frames(src, 3, 5.0)) == 3
    realsense.serials = []  # unplugged
    assert wait_until(lambda: src.counters["disconnect_stall"] == 1 and src.counters["open_failures"], 5.0)
    assert src.status()["connected"] is False
    realsense.serials = ["123"]  # back
    src.slot.take()
    assert wait_until(lambda: src.counters["connects"] == 2, 5.0), src.status()
    assert len(take_frames(src, 3, 5.0)) == 3 and src.status()["connected"] is True
    messages = [r.getMessage() for r in caplog.records]
    assert sum("unplugged?" in m for m in messages) == 1
    assert any("open after" in m for m in messages), messages


def test_a_camera_missing_at_start_is_waited_for_and_logged_once(realsense, running, caplog):
    """Before, the daemon exited (and systemd's start limit could give up on a late-enumerating
    camera). Now start() returns, the source retries with backoff and logs the 1st, 10th, 100th
    attempt, then one line when the camera is there."""
    caplog.set_level("INFO", logger="coopd.camera")
    realsense.serials = []
    src = running(RealSenseConfig(retry_max_s=0.5))
    assert wait_until(lambda: src.counters["open_failures"] >= 3, 5.0)
    assert src.slot.take() is None
    realsense.serials = ["123"]
    assert len(take_frames(src, 2, 5.0)) == 2, src.status()
    failures = src.counters["open_failures"]
    missing = [r.getMessage() for r in caplog.records if "no RealSense device found" in r.getMessage()]
    assert len(missing) == (2 if failures >= 10 else 1) and "attempt 1)" in missing[0], missing
    opened = [r.getMessage() for r in caplog.records if "open after" in r.getMessage()]
    assert len(opened) == 1 and f"after {failures} failed attempts" in opened[0], opened


def test_a_missing_module_still_refuses_to_start(monkeypatch):
    monkeypatch.setitem(sys.modules, "pyrealsense2", None)
    src = RealSenseSource(lambda t: t)
    with pytest.raises(CameraUnavailable, match="not installed"):
        src.start()
    assert src.status()["thread_native_id"] is None  # no thread left behind


@pytest.mark.parametrize(
    "key, value",
    [("width", 0), ("height", 5000), ("fps", 0), ("decimation", 9), ("min_m", -1.0), ("max_m", 70.0),
     ("max_m", 0.05), ("reopen_after_s", 0.1), ("retry_max_s", 1000.0)],
)
def test_bad_realsense_settings_are_config_errors_naming_the_key(key, value):
    with pytest.raises(ConfigError) as e:
        parse_config(f"[camera.realsense]\n{key} = {value}\n")
    assert e.value.key == f"camera.realsense.{key}", str(e.value)


def test_the_daemon_passes_the_realsense_settings_on():
    cfg = parse_config('[camera]\nsource = "realsense:8765"\n[camera.realsense]\nfps = 30\ndecimation = 4\n')
    assert cfg.camera.realsense == RealSenseConfig(fps=30, decimation=4)


def test_stop_while_the_daemon_runs_the_reading_loop_on_its_own_thread(realsense):
    """The daemon calls run() on its thread and stop() from another: the loop ends by itself and
    closes the device; nothing raises on either side."""
    import threading

    src = RealSenseSource(lambda t: t)
    errors = []

    def run():
        try:
            src.run()
        except Exception as e:  # the assertion below shows it
            errors.append(e)

    t = threading.Thread(target=run)
    t.start()
    assert len(take_frames(src, 2, 5.0)) == 2
    src.stop()
    t.join(5.0)
    assert not t.is_alive() and errors == [] and src.status()["connected"] is False

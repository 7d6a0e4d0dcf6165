"""The daemon with source = "realsense" and no camera plugged in: it starts and keeps running
(before: exit 1, and a camera that enumerates late could push the unit into systemd's start
limit), reports the camera as not connected, and opens it once it appears. pyrealsense2 is the
test's stand-in (tests/camera/fake_realsense.py), with the plugged serials read from a file."""

from daemon_harness import ROOT, Coopd, port_block, wait_until, workdir

FAKE_MODULE = """
import sys
sys.path.insert(0, {camera_tests!r})
from fake_realsense import FakeRealSense

class _Plugged(FakeRealSense):
    serials = property(lambda self: open({serials!r}).read().split(), lambda self, value: None)

globals().update(vars(_Plugged().module()))
"""


def test_a_realsense_missing_at_start_is_waited_for_by_a_running_daemon():
    wd = workdir("coopd-rs-")
    serials = wd / "plugged"
    serials.write_text("")
    fake = wd / "fake-pyrealsense2"
    fake.mkdir()
    (fake / "pyrealsense2.py").write_text(
        FAKE_MODULE.format(camera_tests=str(ROOT / "tests" / "camera"), serials=str(serials))
    )
    mav_port, _ = port_block(2)
    d = Coopd(wd, "a", ["--vehicle-id", "1", "--mavlink", f"udpin:127.0.0.1:{mav_port}", "--camera",
                        "realsense", "--no-sharing"], extra_env={"PYTHONPATH": f"{fake}:{ROOT}"}).start()
    try:
        status = d.wait_running(180.0)  # a cold numba cache on a loaded machine: ~50 s of warm-up
        assert status["camera"]["connected"] is False, status["camera"]
        assert wait_until(lambda: d.status()["camera"]["counters"].get("open_failures", 0) >= 2, 20.0)
        serials.write_text("123")  # plugged in
        status = wait_until(lambda: (s := d.status()) and s["camera"]["connected"] and s, 30.0)
        assert status, d.log_text()[-2000:]
        log = d.log_text()
        assert log.count("no RealSense device found") == 1, log[-3000:]
        assert "attempt 1)" in log and "open after" in log and "streaming 640x480@15" in log, log[-3000:]
        print([ln for ln in log.splitlines() if "camera" in ln.lower()][:6])
        rc, _ = d.terminate()
        assert rc == 0, d.log_text()[-2000:]
    finally:
        d.stop()

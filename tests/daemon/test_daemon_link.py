"""The daemon's FC link as the operator sees it: `coopctl status` tells a system-id mismatch within
5 s of the FC's first heartbeat (in-process daemon, a pymavlink FC on loopback UDP)."""

import shutil
import socket
import threading

import pytest
from daemon_harness import in_process_memory_mb, workdir
from pymavlink.dialects.v20 import common as mav

from coopd.cli.daemon_commands import format_status
from coopd.daemon import control
from coopd.daemon.config import from_dict
from coopd.daemon.main import main
from coopd.daemon.service import Daemon, StartupError, link_config
from tests.camera.fake_driver import FakeDriver, frame_bytes, header
from tests.loopback_fc import LoopbackFc, UdpChannel, free_port


@pytest.fixture
def wd():
    d = workdir("coopd-link-")
    yield d
    shutil.rmtree(d, ignore_errors=True)


def start_daemon(wd, mav_port: int, vehicle_id: int = 1, camera_stall_s: float = 2.0):
    config = from_dict({
        "vehicle": {"id": vehicle_id, "mavlink": f"udpin:127.0.0.1:{mav_port}"},
        "camera": {"source": f"socket:{wd}/camera.sock", "stall_timeout_s": camera_stall_s},
        "sharing": {"enabled": False},
        "daemon": {"state_dir": str(wd / "state"), "control_socket": str(wd / "control.sock"),
                   "memory_mb": in_process_memory_mb()},
    })
    d = Daemon(config)
    d.start()
    runner = threading.Thread(target=d.run, daemon=True)
    runner.start()
    return d, runner


def stop_daemon(d, runner) -> None:
    d.request_stop("test")
    runner.join(5)
    d.shutdown()


def test_coopctl_status_shows_a_system_id_mismatch_within_5_s(wd):
    port = free_port()
    d, runner = start_daemon(wd, port, vehicle_id=1)
    fc = LoopbackFc(UdpChannel(socket.AF_INET, send_to=("127.0.0.1", port)), system_id=7)
    try:
        status = lambda: control.request(d.config.daemon.control_socket, "status")[0]  # noqa: E731
        shown = lambda: status()["link"]["reason"] == "system_id_mismatch"  # noqa: E731
        assert fc.run_until(shown, seconds=5.0, period=0.2), status()["link"]
        text = format_status(status())
        assert "connecting: system id mismatch: expecting system 1 (vehicle.id), autopilot system 7" in text
    finally:
        fc.close()
        stop_daemon(d, runner)


def test_the_gcs_hears_odometry_lost_and_back_and_the_heartbeat_follows_health(wd):
    """The FC (here a loopback pymavlink FC, which a real one forwards to the GCS) receives coopd's
    STATUSTEXTs with their severities, and coopd's HEARTBEAT goes STANDBY (odometry, no camera yet)
    -> CRITICAL (odometry stopped) -> STANDBY (back)."""
    port = free_port()
    d, runner = start_daemon(wd, port, vehicle_id=1)
    fc = LoopbackFc(UdpChannel(socket.AF_INET, send_to=("127.0.0.1", port)), system_id=1)
    clock = [10.0]

    def odometry(f):
        clock[0] += 0.05
        f.odometry(clock[0])

    def heard(severity, text):
        return any(m.severity == severity and m.text == text for m in fc.messages("STATUSTEXT"))

    def coopd_status():
        ours = mav.MAV_COMP_ID_ONBOARD_COMPUTER
        beats = [m for m in fc.messages("HEARTBEAT") if m.get_srcComponent() == ours]
        return beats[-1].system_status if beats else None

    def standby_and_back():
        return (heard(mav.MAV_SEVERITY_NOTICE, "coopd: odometry ok")
                and coopd_status() == mav.MAV_STATE_STANDBY)

    def critical_and_warned():
        return (heard(mav.MAV_SEVERITY_WARNING, "coopd: no odometry, mapping paused")
                and coopd_status() == mav.MAV_STATE_CRITICAL)

    try:
        assert fc.run_until(standby_and_back, seconds=10.0, period=0.05, send=odometry)
        assert heard(mav.MAV_SEVERITY_NOTICE, "coopd: FC link up")
        assert fc.run_until(critical_and_warned, seconds=10.0, period=0.05)
        fc.received.clear()
        # back within 10 s: the heartbeat says so; the same text again is held back (one per 10 s)
        back = lambda: coopd_status() == mav.MAV_STATE_STANDBY  # noqa: E731
        assert fc.run_until(back, seconds=10.0, period=0.05, send=odometry)
        counters = d.link.status()["counters"]
        assert counters["statustext_sent"] == 3 and counters["statustext_repeats"] == 1
    finally:
        fc.close()
        stop_daemon(d, runner)


def test_the_gcs_hears_a_camera_stall_and_the_heartbeat_goes_critical(wd):
    """Odometry and camera frames flowing: ACTIVE; the camera driver stops sending (connection kept
    open): a WARNING STATUSTEXT and CRITICAL."""
    port = free_port()
    fc_clock = [10.0]
    sending = threading.Event()
    sending.set()

    def camera_script(conn, index, stopping):
        seq = 0
        while not stopping.is_set() and index == 0 and sending.is_set():
            conn.sendall(frame_bytes(header(seq=seq, t_us=int(fc_clock[0] * 1e6))))
            seq += 1
            stopping.wait(0.1)
        stopping.wait(10.0)  # silent, connection open: a stalled camera

    driver = FakeDriver(str(wd / "camera.sock"), camera_script)
    d, runner = start_daemon(wd, port, vehicle_id=1, camera_stall_s=0.5)
    fc = LoopbackFc(UdpChannel(socket.AF_INET, send_to=("127.0.0.1", port)), system_id=1)

    def odometry(f):
        fc_clock[0] += 0.05
        f.odometry(fc_clock[0])

    def heard(severity, prefix):
        return any(m.severity == severity and m.text.startswith(prefix) for m in fc.messages("STATUSTEXT"))

    def coopd_status():
        ours = mav.MAV_COMP_ID_ONBOARD_COMPUTER
        beats = [m for m in fc.messages("HEARTBEAT") if m.get_srcComponent() == ours]
        return beats[-1].system_status if beats else None

    try:
        active = lambda: (coopd_status() == mav.MAV_STATE_ACTIVE  # noqa: E731
                          and heard(mav.MAV_SEVERITY_NOTICE, "coopd: camera frames ok"))
        assert fc.run_until(active, seconds=15.0, period=0.05, send=odometry), d.health()
        sending.clear()
        stalled = lambda: (heard(mav.MAV_SEVERITY_WARNING, "coopd: camera stalled, no frame for")  # noqa: E731
                           and coopd_status() == mav.MAV_STATE_CRITICAL)
        assert fc.run_until(stalled, seconds=10.0, period=0.05, send=odometry), d.health()
    finally:
        fc.close()
        stop_daemon(d, runner)
        driver.close()


def test_signing_key_file_is_read_at_start(wd):
    key_file = wd / "mavlink.key"
    key_file.write_text(bytes(range(32)).hex() + "\n")
    config = from_dict({"vehicle": {"signing_key_file": str(key_file)}})
    assert link_config(config).signing_key == bytes(range(32))
    assert link_config(from_dict({})).signing_key is None
    key_file.write_text("not a key")
    with pytest.raises(StartupError, match="vehicle.signing_key_file: .*64 hexadecimal"):
        link_config(config)


def test_check_config_reads_the_signing_key_file(wd, capsys):
    key_file = wd / "mavlink.key"
    key_file.write_text("too short")
    assert main(["--no-config", "--check-config", "--mavlink", "udpin://:14540"]) == 0
    (wd / "c.toml").write_text(f'[vehicle]\nsigning_key_file = "{key_file}"\n')
    assert main(["--config", str(wd / "c.toml"), "--check-config"]) == 2
    assert "vehicle.signing_key_file" in capsys.readouterr().err
    key_file.write_text(bytes(range(32)).hex())
    assert main(["--config", str(wd / "c.toml"), "--check-config"]) == 0

"""The daemon's FC link as the operator sees it: `coopctl status` tells a system-id mismatch within
5 s of the FC's first heartbeat (in-process daemon, a pymavlink FC on loopback UDP)."""

import shutil
import socket
import threading

import pytest
from daemon_harness import in_process_memory_mb, workdir

from coopd.cli.daemon_commands import format_status
from coopd.daemon import control
from coopd.daemon.config import from_dict
from coopd.daemon.service import Daemon
from tests.loopback_fc import LoopbackFc, UdpChannel, free_port


@pytest.fixture
def wd():
    d = workdir("coopd-link-")
    yield d
    shutil.rmtree(d, ignore_errors=True)


def start_daemon(wd, mav_port: int, vehicle_id: int = 1, **vehicle_keys):
    config = from_dict({
        "vehicle": {"id": vehicle_id, "mavlink": f"udpin:127.0.0.1:{mav_port}", **vehicle_keys},
        "camera": {"source": f"socket:{wd}/no-camera.sock"},
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

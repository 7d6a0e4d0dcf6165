"""The obstacles reporter: global map overlaid with the live local map, no pose -> no data, the
window bound; and the daemon sending OBSTACLE_DISTANCE at the configured rate to a loopback FC."""

import shutil
import socket
import threading
import time

import numpy as np
import pytest
from daemon_harness import in_process_memory_mb, workdir
from pymavlink.dialects.v20 import common as mav

from coopd.cli.daemon_commands import format_status
from coopd.daemon.config import ObstaclesConfig, from_dict
from coopd.daemon.obstacles import ObstacleReporter
from coopd.daemon.service import Daemon, StartupError
from coopd.grid import OccupancyGrid
from coopd.grid.sectors import NO_DATA, SECTORS
from coopd.vehicle.pose_buffer import PoseSample
from tests.loopback_fc import LoopbackFc, UdpChannel, free_port

RES = 0.1
CONFIG = ObstaclesConfig(enabled=True, min_distance_m=0.3, max_distance_m=4.0)
AT_ORIGIN = PoseSample(1.5, np.zeros(3), np.array([1.0, 0, 0, 0]))


def room(value=5) -> OccupancyGrid:
    g = OccupancyGrid.empty((120, 120, 30), RES)
    g.cells[...] = value
    return g


class Fixture:
    """A reporter on a local map (with its lock), an optional global map and a settable pose."""

    def __init__(self, local: OccupancyGrid, global_map: OccupancyGrid | None,
                 pose=AT_ORIGIN):
        self.local, self.lock = local, threading.Lock()
        self.global_map, self.sample, self.sent = global_map, pose, []
        self.reporter = ObstacleReporter(
            CONFIG, RES, lambda: (self.local, self.lock),
            lambda: None if self.global_map is None else (self.global_map, None),
            lambda: self.sample, lambda *message: self.sent.append(message))


def test_a_wall_only_a_peer_mapped_is_reported_and_the_local_map_wins_where_it_knows():
    merged = room()
    merged.block((20, -60, -15), (20, 59, 14))[...] = 90  # wall 2 m ahead in the global map
    f = Fixture(room(-1), merged)  # this vehicle never saw anything
    f.reporter.update()
    distances, min_cm, max_cm, t_fc = f.sent[-1]
    assert distances[0] == 195 and (min_cm, max_cm, t_fc) == (30, 400, 1.5)
    assert f.reporter.counters == {"sent": 1, "no_pose": 0, "with_global": 1, "errors": 0}
    f.local.block((20, -60, -15), (20, 59, 14))[...] = 0  # the live map saw the wall gone (a door)
    f.reporter.update()
    assert f.sent[-1][0][0] == 401
    status = f.reporter.status()
    assert status["sectors_free"] == SECTORS and status["update_ms"]["max"] >= status["update_ms"]["mean"]


def test_no_global_map_reads_the_local_map_and_unknown_stays_no_data():
    f = Fixture(room(-1), None)
    f.reporter.update()
    assert np.all(f.sent[-1][0] == NO_DATA) and f.reporter.counters["with_global"] == 0


def test_without_a_fresh_pose_every_sector_is_no_data():
    f = Fixture(room(), room(), pose=None)
    f.reporter.update()
    distances, _, _, t_fc = f.sent[-1]
    assert np.all(distances == NO_DATA) and t_fc is None and f.reporter.counters["no_pose"] == 1
    assert f.reporter.status()["nearest_m"] is None


def test_a_window_too_large_is_refused_at_start():
    big = ObstaclesConfig(enabled=True, max_distance_m=30.0, band_below_m=2.0, band_above_m=2.0)
    with pytest.raises(ValueError, match="lower max_distance_m"):
        ObstacleReporter(big, 0.05, None, None, None, None)


@pytest.fixture
def wd():
    d = workdir("coopd-obstacles-")
    yield d
    shutil.rmtree(d, ignore_errors=True)


def daemon_config(wd, port: int, **obstacles):
    return from_dict({
        "vehicle": {"id": 1, "mavlink": f"udpin:127.0.0.1:{port}"},
        "camera": {"source": f"socket:{wd}/camera.sock"},
        "sharing": {"enabled": False},
        "obstacles": obstacles,
        "daemon": {"state_dir": str(wd / "state"), "control_socket": str(wd / "control.sock"),
                   "memory_mb": in_process_memory_mb()},
    })


def test_the_daemon_sends_obstacle_distance_at_the_configured_rate(wd):
    port = free_port()
    d = Daemon(daemon_config(wd, port, enabled=True, rate_hz=10.0, max_distance_m=4.0), merge_fn=None)
    d.start()
    runner = threading.Thread(target=d.run, daemon=True)
    runner.start()
    fc = LoopbackFc(UdpChannel(socket.AF_INET, send_to=("127.0.0.1", port)), system_id=1)
    clock = [10.0]

    def odometry(f):
        clock[0] += 0.05
        f.odometry(clock[0])

    try:
        assert fc.run_until(lambda: len(fc.messages("OBSTACLE_DISTANCE")) >= 3, 10.0, 0.05, odometry)
        fc.received.clear()
        t0 = time.monotonic()
        fc.run_until(lambda: False, seconds=2.0, period=0.05, send=odometry)
        elapsed = time.monotonic() - t0
        got = fc.messages("OBSTACLE_DISTANCE")
        # never faster than asked (one update may straddle each end); slower only on a starved machine
        assert 0.5 * 10.0 * elapsed <= len(got) <= 10.0 * elapsed + 2, (len(got), elapsed)
        m = got[-1]
        assert m.frame == mav.MAV_FRAME_BODY_FRD and m.increment_f == 5.0 and m.angle_offset == 0.0
        assert (m.min_distance, m.max_distance) == (30, 400) and len(m.distances) == SECTORS
        assert all(v == NO_DATA for v in m.distances)  # nothing mapped yet: no data, never free
        assert m.get_srcComponent() == mav.MAV_COMP_ID_ONBOARD_COMPUTER
        status = d.handle_status({})["obstacles"]
        # only updates before the first odometry went without a pose
        assert status["enabled"] and status["sent"] >= len(got) + status["no_pose"]
        assert any(t["role"] == "obstacles" for t in d.priorities.report())
        row = [line for line in format_status(d.handle_status({})).splitlines() if "obstacles" in line]
        assert row and "OBSTACLE_DISTANCE sent at 10.0 Hz" in row[0] and "72 sectors no data" in row[0]
    finally:
        fc.close()
        d.request_stop("test")
        runner.join(5)
        d.shutdown()


def fc_params_answering(values: dict[str, float]):
    """A loopback FC's send hook: odometry, and PARAM_VALUE for each PARAM_REQUEST_READ of a name in
    values (REAL32, as PX4 sends CP_DIST)."""
    clock = [10.0]

    def send(fc):
        clock[0] += 0.05
        fc.odometry(clock[0])
        for m in fc.messages("PARAM_REQUEST_READ"):
            if m.param_id in values and not getattr(m, "answered", False):
                m.answered = True
                fc.mav.send(fc.mav.param_value_encode(m.param_id.encode(), values[m.param_id],
                                                      mav.MAV_PARAM_TYPE_REAL32, 1, 0))

    return send


def test_by_default_it_sends_only_while_the_fc_says_it_uses_obstacle_data(wd, caplog):
    """The default config: coopd asks the FC (PX4 here) for CP_DIST; -1 (collision prevention off):
    nothing is sent; the FC reporting CP_DIST = 1 m (after a ground station set it): sending starts,
    each change one log line."""
    port = free_port()
    d = Daemon(daemon_config(wd, port), merge_fn=None)
    caplog.set_level("INFO", logger="coopd.daemon")
    d.start()
    runner = threading.Thread(target=d.run, daemon=True)
    runner.start()
    fc = LoopbackFc(UdpChannel(socket.AF_INET, send_to=("127.0.0.1", port)), system_id=1)
    values = {"CP_DIST": -1.0}
    send = fc_params_answering(values)
    try:
        asked = lambda: d.link.counters["obstacle_params_heard"] >= 1  # noqa: E731
        assert fc.run_until(asked, 10.0, 0.05, send), d.link.counters
        assert [m.param_id for m in fc.messages("PARAM_REQUEST_READ")][:1] == ["CP_DIST"]
        fc.run_until(lambda: False, seconds=1.0, period=0.05, send=send)
        status = d.handle_status({})["obstacles"]
        assert not fc.messages("OBSTACLE_DISTANCE") and not status["sending"], status
        assert "CP_DIST = -1" in status["fc"]
        row = [line for line in format_status(d.handle_status({})).splitlines() if "obstacles" in line]
        assert row and "not sending; FC: CP_DIST = -1 m (collision prevention off)" in row[0], row
        # a ground station turns collision prevention on: the FC sends the new PARAM_VALUE unasked
        fc.mav.send(fc.mav.param_value_encode(b"CP_DIST", 1.0, mav.MAV_PARAM_TYPE_REAL32, 1, 0))
        assert fc.run_until(lambda: len(fc.messages("OBSTACLE_DISTANCE")) >= 3, 10.0, 0.05, send)
        status = d.handle_status({})["obstacles"]
        assert status["sending"] and status["fc"] == "CP_DIST = 1 m" and not status["enabled"], status
        lines = [r.getMessage() for r in caplog.records if r.getMessage().startswith("obstacles:")]
        assert len(lines) == 2 and "not sending" in lines[0] and "the FC uses them: CP_DIST = 1 m" in lines[1]
    finally:
        fc.close()
        d.request_stop("test")
        runner.join(5)
        d.shutdown()


def test_obstacles_off_sends_nothing_and_a_huge_window_stops_the_start(wd):
    port = free_port()
    d = Daemon(daemon_config(wd, port, when_fc_asks=False), merge_fn=None)
    assert d.obstacles is None and not d.handle_status({})["obstacles"]["sending"]
    assert not d.link.config.watch_obstacle_demand  # the FC is not even asked
    with pytest.raises(StartupError, match="obstacles"):
        Daemon(daemon_config(wd, free_port(), enabled=True, max_distance_m=30.0, band_below_m=5.0),
               merge_fn=None)

"""scripts/demo's daemon settings and report lines, without flying: every drone's coopd sends
OBSTACLE_DISTANCE (and records with --record), and the report says what was sent and received."""

import importlib.util
from pathlib import Path
from types import SimpleNamespace

import pytest

from coopd.daemon.config import load_config
from firmware_sim.netns import LoopbackLab
from firmware_sim.swarm import Swarm, SwarmSettings, render_config

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def demo():
    spec = importlib.util.spec_from_file_location("coopd_demo_script", ROOT / "scripts" / "demo.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.parametrize("record", [False, True])
def test_every_demo_daemon_sends_obstacle_distance(demo, tmp_path, record):
    recordings = tmp_path / "recordings"
    swarm = Swarm(SwarmSettings(drones=2, network="loopback", swarm_key=b"k" * 32,
                                config=demo.demo_config(SimpleNamespace(record=record), recordings)),
                  workdir=tmp_path, say=lambda _: None)
    swarm.lab = LoopbackLab()
    for host in (1, 2):
        swarm.lab.add_host(host)
    (tmp_path / "swarm.key").write_bytes(b"k" * 32)
    for i in range(2):
        path = tmp_path / f"coopd{i}.toml"
        path.write_text(render_config(swarm.config_sections(i)))
        cfg = load_config(path)  # the daemon's own validation accepts it
        assert cfg.obstacles.enabled
        assert cfg.viewer.record_dir == (str(recordings) if record else "")


def test_obstacles_line(demo):
    status = {"obstacles": {"enabled": True, "sending": True, "sent": 1030, "rate_hz": 10.0,
                            "with_global": 1006, "no_pose": 4, "nearest_m": 0.3}}
    line = demo.obstacles_line(status, 1124)
    assert line.startswith("obstacles: 1030 OBSTACLE_DISTANCE sent at 10.0 Hz (1006 with the global map, "
                           "4 without a pose), last nearest 0.3 m; the FC has received 1124")
    off = {"enabled": False, "sending": False, "sent": 0, "fc": "CP_DIST = -1 m (collision prevention off)"}
    assert demo.obstacles_line({"obstacles": off}, 0) == (
        "obstacles: not sent (FC: CP_DIST = -1 m (collision prevention off))")
    assert "nearest -; the FC has received -" in demo.obstacles_line(
        {"obstacles": {"enabled": True, "sending": True, "sent": 0, "nearest_m": None}}, None)

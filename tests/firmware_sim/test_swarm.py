"""The simulated swarm (firmware_sim.swarm) and scripts/demo on top of it: daemons on their own
addresses (network namespaces when root), maps shared and merged within tolerance of the truth,
and nothing left behind, also when the demo is interrupted."""

import os
import signal
import subprocess
import sys
import time
import tomllib
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from coopd.daemon.config import load_config
from coopd.geometry import invert
from firmware_sim.netns import netns_unavailable_reason
from firmware_sim.swarm import NETNS_TAG, Swarm, SwarmSettings, render_config
from tests.ports import process_slot

ROOT = Path(__file__).resolve().parents[2]
PORTS = 20200 + process_slot(20) * 20  # MAVLink ports from here, map servers on PORTS + 10
NET = 2 + process_slot(98)  # this run's own swarm and FC networks (10.214.NET, 10.215.NET)


def our_namespaces() -> list[str]:
    if netns_unavailable_reason():
        return []
    out = subprocess.run(["ip", "netns", "list"], capture_output=True, text=True, timeout=10).stdout
    return [line.split()[0] for line in out.splitlines() if line.startswith(f"{NETNS_TAG}-{os.getpid()}-")]


def test_render_config_is_valid_toml_with_overrides(tmp_path):
    swarm = Swarm(SwarmSettings(drones=2, network="loopback", swarm_key=b"k" * 32,
                                config={"merging": {"period_s": 7.5, "enabled": True}}), workdir=tmp_path,
                  say=lambda _: None)
    from firmware_sim.netns import LoopbackLab

    swarm.lab = LoopbackLab()
    swarm.lab.add_host(1)
    swarm.lab.add_host(2)
    text = render_config(swarm.config_sections(1))
    parsed = tomllib.loads(text)
    assert parsed["vehicle"]["id"] == 2
    assert parsed["merging"] == {"period_s": 7.5, "enabled": True}
    assert parsed["sharing"]["listen_host"] == swarm.address(1)
    assert parsed["sharing"]["peers"] == [swarm.lab.range_spec(2)]
    assert parsed["sharing"]["swarm_key_file"].endswith("swarm.key")
    cfg_path = tmp_path / "c.toml"
    cfg_path.write_text(text)
    (tmp_path / "swarm.key").write_bytes(b"k" * 32)
    cfg = load_config(cfg_path)  # the daemon's own validation accepts what the swarm writes
    assert cfg.vehicle.id == 2


def test_the_live_view_is_served_on_each_drone_address(tmp_path):
    """viewer_port: each daemon serves its view on its swarm address; open only where that address is
    not loopback (netns), which the daemon's own validation requires."""
    from firmware_sim.netns import LoopbackLab

    swarm = Swarm(SwarmSettings(drones=2, network="loopback", open=True, viewer_port=8765,
                                config={"viewer": {"record_dir": str(tmp_path / "rec")}}),
                  workdir=tmp_path, say=lambda _: None)
    swarm.lab = LoopbackLab()
    for lab in (swarm.lab, NetnsLabAddresses("10.214.9")):
        swarm.lab = lab
        for i in (0, 1):
            lab.add_host(i + 1)
            viewer = swarm.config_sections(i)["viewer"]
            assert viewer["host"] == lab.address(i + 1) and viewer["port"] == 8765
            assert viewer["open"] == lab.address(i + 1).startswith("10.")
            assert viewer["record_dir"] == str(tmp_path / "rec")  # the settings' config still applies
            assert swarm.viewer_url(i) == f"ws://{lab.address(i + 1)}:8765"
            path = tmp_path / f"c{i}.toml"
            path.write_text(render_config(swarm.config_sections(i)))
            assert load_config(path).viewer.enabled
    assert Swarm(SwarmSettings(), workdir=tmp_path, say=lambda _: None).viewer_url(0) is None


class NetnsLabAddresses:
    """A netns lab's addresses without creating namespaces (the config the swarm writes for them)."""

    mode = "netns"

    def __init__(self, subnet: str):
        self.subnet = subnet

    def fc_addresses(self, i: int) -> tuple[str, str]:
        return f"10.215.9.{4 * i + 1}", f"10.215.9.{4 * i + 2}"

    def add_host(self, i: int) -> str:
        return self.address(i)

    def address(self, i: int) -> str:
        return f"{self.subnet}.{i}"

    def range_spec(self, n: int) -> str:
        return f"{self.subnet}.1-{self.subnet}.{n}"


@pytest.mark.slow
def test_two_drones_share_merge_and_leave_nothing_behind():
    settings = SwarmSettings(drones=2, mavlink_base=PORTS, sharing_port=PORTS + 10, speed=2.0,
                             subnet=f"10.214.{NET}", fc_subnet=f"10.215.{NET}")
    swarm = Swarm(settings, say=print)
    workdir = swarm.workdir
    try:
        swarm.start()
        assert swarm.network_mode == ("loopback" if netns_unavailable_reason() else "netns")
        swarm.fly()
        swarm.wait_for(swarm.landed, 240, "every drone landed")
        assert swarm.merge_until_converged(limit_s=150), [swarm.status(i) for i in range(2)]
        statuses = swarm.statuses()
        wrong = {}
        for i in range(2):
            errors = swarm.offset_errors(i, statuses)
            assert set(errors) == {2 - i}
            wrong.update({f"{i + 1}<-{v}": e for v, e in errors.items()
                          if not (e["error_m"] < 0.3 and e["error_deg"] < 3.0)})
            peers = {p["vehicle_id"]: p for p in statuses[i]["peers"]}
            assert peers[2 - i]["address"].split(":")[0] == swarm.address(1 - i)
    finally:
        swarm.stop()
    assert not workdir.exists()
    assert our_namespaces() == []
    assert all(not d.running() for d in swarm.daemons)
    assert not wrong, f"merged off the truth (> 0.3 m or 3 deg): {wrong}"


@pytest.mark.slow
def test_demo_interrupted_stops_every_process_and_namespace(tmp_path):
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    # Ctrl-C as from a terminal, also when this test runs in a background job (which ignores SIGINT
    # and would hand that on to the demo)
    proc = subprocess.Popen([sys.executable, str(ROOT / "scripts" / "demo.py"), "--drones", "2",
                             "--port-base", str(PORTS + 2), "--out", str(tmp_path)],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env, cwd=ROOT,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    lines = []
    try:
        deadline = time.monotonic() + 240
        for line in proc.stdout:
            lines.append(line)
            if "coopd daemons mapping" in line or time.monotonic() > deadline:
                break
        assert any("coopd daemons mapping" in line for line in lines), "".join(lines)
        workdir = next(w for w in lines[-1].split() if w.startswith("/tmp/coopd-swarm-"))
        children = subprocess.run(["pgrep", "-f", workdir], capture_output=True, text=True).stdout.split()
        assert len(children) == 2  # one coopd per drone
        proc.send_signal(signal.SIGINT)
        rest, _ = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 130, "".join(lines) + rest
    assert "every process and namespace it made is gone" in rest
    assert subprocess.run(["pgrep", "-f", workdir], capture_output=True).returncode == 1
    assert not Path(workdir).exists()
    if not netns_unavailable_reason():
        listing = subprocess.run(["ip", "netns", "list"], capture_output=True, text=True, timeout=10).stdout
        assert f"{NETNS_TAG}-{proc.pid}-" not in listing


def test_tracks_in_map_carry_other_drones_through_the_merge_estimate():
    world_from_map = {0: np.eye(4), 1: np.array([[0.0, -1, 0, 0], [1, 0, 0, 2], [0, 0, 1, 0], [0, 0, 0, 1]])}
    world_from_map[0][:3, 3] = [1.0, 0.0, 0.0]
    flights = {j: np.c_[np.arange(3.0), np.arange(3.0) + j, np.full(3, 2.0 * j), np.ones(3), np.ones((3, 4))]
               for j in range(3)}
    shift = np.array([[1.0, 0, 0, 0.5], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]])  # an estimate 0.5 m off
    merged = {2: {"transform": (shift @ invert(world_from_map[0]) @ world_from_map[1]).tolist()}}
    fake = SimpleNamespace(settings=SimpleNamespace(drones=3), sim=SimpleNamespace(trajectory=flights.get),
                           map_to_world=lambda j, s: world_from_map[j], merged_vehicles=lambda s: merged)
    tracks, left_out = Swarm.tracks_in_map(fake, 0, [{"link": {}}, {"link": {}}, {"link": {}}])
    assert left_out == [3] and sorted(tracks) == [1, 2]
    assert np.allclose(tracks[1], flights[0][:, 1:3] - [1.0, 0.0])  # its own: where its map frame truly is
    assert np.allclose(tracks[2], flights[1][:, 1:3] - [0.5, 0.0])  # through the estimate, off by its error

"""An FC reboot in flight and an estimator position reset: silence, a new time base and sequence, the
estimator's new frame, and the vehicle carrying on."""

from __future__ import annotations

import math

import numpy as np
import pytest

from firmware_sim.frames import ENU_TO_NED
from firmware_sim.simulation import Simulation
from firmware_sim.worlds import build_world

from .mavlink_client import Client


@pytest.fixture(scope="module")
def house():
    return build_world("small_house", seed=0)


@pytest.fixture
def flying(house, port_block):
    """One vehicle flying its built-in route, stepped in-process, and a client on its onboard port."""
    sim = Simulation(house, 1, seed=2, noise="none", camera=None, mavlink_base_port=port_block,
                     route="builtin")
    client = Client(port_block, 1)
    sim.step(0.1)
    assert client.wait("HEARTBEAT", timeout=2) is not None
    sim.step(8.0)  # took off, on its way along the route
    client.drain()
    yield sim, client
    sim.stop()
    client.conn.close()


def odometry_now(sim, client):
    """The next ODOMETRY after a short step, as (time since boot s, local ENU position, reset counter)."""
    client.drain()
    sim.step(0.1)
    msgs = [m for m in client.drain() if m.get_type() == "ODOMETRY"]
    assert msgs, "no ODOMETRY"
    m = msgs[-1]
    return m.time_usec * 1e-6, ENU_TO_NED.T @ np.array([m.x, m.y, m.z]), m.reset_counter


def local_of_world(sim, t_frame: float, p_world) -> np.ndarray:
    """Drift-free local ENU of a world point in the vehicle's frame in use at sim time t_frame."""
    from firmware_sim.frames import rot_z

    origin, yaw = sim.vehicle(0).odometry.frame_at(t_frame)
    return rot_z(yaw).T @ (np.asarray(p_world) - origin)


def test_reboot_goes_silent_restarts_time_and_sequence_and_moves_the_origin(flying):
    sim, client = flying
    t_before, _, _ = odometry_now(sim, client)
    assert t_before > 7.0
    t_reboot = sim.time
    at_reboot = sim.true_pose(0)[0]
    sim.reboot_fc(0, downtime_s=1.5, move_origin=True, turn_rad=0.3)
    sim.step(1.2)
    assert client.drain() == [], "the endpoint must be silent while the FC reboots"
    sim.step(0.4)
    after = client.drain()
    assert after, "the endpoint came back"
    assert after[0].get_seq() < 5, "a rebooted FC starts a new MAVLink sequence"
    t_after, pos, counter = odometry_now(sim, client)
    assert t_after < 1.0, "time since boot restarted"
    assert counter == 0
    held = sim.true_pose(0)[0]
    assert np.linalg.norm(held - at_reboot) < 0.5, "the emulated airframe holds through the reboot"
    assert np.linalg.norm(pos) < 0.3, "the new local origin is where the vehicle was at restart"
    # The truth of the frame change carries the new frame's points into the old one.
    t_new = sim.time
    old_frame_truth = local_of_world(sim, t_reboot - 0.1, sim.true_pose(0)[0])
    mapped = sim.fc_frame_transform(0, t_reboot - 0.1, t_new) @ np.append(pos, 1.0)
    assert np.linalg.norm(mapped[:3] - old_frame_truth) < 0.2
    assert sim.vehicle(0).fc_reboots == 1
    # The mission continues in the new frame: the vehicle moves on and stays armed.
    sim.step(6.0)
    assert sim.vehicle(0).fc.armed
    assert np.linalg.norm(sim.true_pose(0)[0][:2] - held[:2]) > 1.0


def test_reboot_keeping_the_origin_continues_the_frame(flying):
    sim, client = flying
    _, before, _ = odometry_now(sim, client)
    sim.reboot_fc(0, downtime_s=1.0, move_origin=False)
    sim.step(1.2)
    t_after, after, _ = odometry_now(sim, client)
    assert t_after < 1.0
    assert np.linalg.norm(after - before) < 0.6


def test_estimator_reset_counts_and_jumps(flying):
    sim, client = flying
    _, before, counter = odometry_now(sim, client)
    assert counter == 0
    transform = sim.reset_estimator(0, shift_m=(3.0, -2.0, 0.0))
    t_after, after, counter = odometry_now(sim, client)
    assert counter == 1 and t_after > 8.0, "a reset keeps the time base"
    expected = transform[:3, :3] @ before + transform[:3, 3]
    assert np.linalg.norm(after - expected) < 0.4
    assert np.linalg.norm(after - before) > 3.0
    sim.step(3.0)
    assert sim.vehicle(0).fc.armed, "the flight controller's targets moved with its frame"


def test_reboot_arguments_are_checked(flying):
    sim, _ = flying
    for bad in (dict(downtime_s=-1), dict(downtime_s=math.inf), dict(turn_rad=7.0)):
        with pytest.raises(ValueError):
            sim.reboot_fc(0, **bad)
    sim.reboot_fc(0, downtime_s=1.0)
    with pytest.raises(RuntimeError):
        sim.reboot_fc(0)
    with pytest.raises(ValueError):
        sim.reset_estimator(0, shift_m=(math.nan, 0, 0))

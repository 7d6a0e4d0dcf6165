"""Vehicle physics, flight modes, odometry frames, drift and the built-in routes (in-process, no sockets)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from firmware_sim.flight import MAIN_AUTO, SUB_LOITER
from firmware_sim.frames import ENU_TO_NED, enu_flu_to_ned_frd, euler_zyx, quat_to_mat
from firmware_sim.odometry import NoiseConfig
from firmware_sim.simulation import Simulation
from firmware_sim.worlds import build_world


@pytest.fixture(scope="module")
def house():
    return build_world("small_house", seed=0)


def test_rests_on_the_floor_when_disarmed(house):
    sim = Simulation(house, 2, seed=0, mavlink=False, camera=None)
    z0 = sim.true_pose(0)[0][2]
    sim.step(2.0)
    p, q = sim.true_pose(0)
    assert abs(p[2] - z0) < 0.02 and 0.0 < p[2] < 0.1
    assert quat_to_mat(q)[2, 2] > 0.999


def test_takeoff_hold_reposition_land(house):
    sim = Simulation(house, 1, seed=0, mavlink=False, camera=None, noise="none")
    v = sim.vehicle(0)
    sim.step(0.1)
    assert v.fc.takeoff(sim.time, 1.5) == 2  # denied while disarmed
    assert v.fc.arm(sim.time) == 0
    assert v.fc.takeoff(sim.time, 1.5) == 0
    sim.step(5.0)
    p, _ = sim.true_pose(0)
    assert abs(p[2] - 1.55) < 0.05
    assert (v.fc.main_mode, v.fc.sub_mode) == (MAIN_AUTO, SUB_LOITER)
    assert v.fc.disarm(sim.time) == 1  # refused in the air without force
    start = p.copy()
    s = sim.estimated_state(v)
    target = s.pos + np.array([0.0, 1.0, 0.0])  # 1 m along the initial heading (local ENU y)
    assert v.fc.reposition(sim.time, target, None) == 0
    sim.step(5.0)
    p, _ = sim.true_pose(0)
    heading = sim.vehicle(0).true_start_pose[3]
    np.testing.assert_allclose(p[:2] - start[:2], [math.cos(heading), math.sin(heading)], atol=0.1)
    v.fc.land(sim.time)
    sim.step(5.0)
    p, _ = sim.true_pose(0)
    assert p[2] < 0.1 and not v.fc.armed and v.fc.landed


def test_thrust_limit_bounds_climb_rate(house):
    sim = Simulation(house, 1, seed=0, mavlink=False, camera=None, noise="none")
    v = sim.vehicle(0)
    v.fc.arm(0.0)
    v.fc.takeoff(0.0, 2.5)
    speeds = []
    for _ in range(100):
        sim.step(0.02)
        speeds.append(sim.true_velocity(0)[2])
    assert max(speeds) < 1.3  # the climb-rate limit plus a little overshoot


def test_odometry_reports_in_each_vehicles_start_frame(house):
    sim = Simulation(house, 3, seed=2, mavlink=False, camera=None, noise="none")
    for i, v in enumerate(sim.vehicles):
        s = sim.estimated_state(v)
        p_ned = ENU_TO_NED @ s.pos
        assert np.linalg.norm(p_ned[:2]) < 1e-6  # origin = start position
        yaw_ned = euler_zyx(enu_flu_to_ned_frd(s.rot))[2]
        assert abs(yaw_ned) < 1e-6, i  # x axis = initial heading
    headings = [v.true_start_pose[3] for v in sim.vehicles]
    assert np.ptp(headings) > 0.5  # so the frames really differ


def test_world_frame_option(house):
    sim = Simulation(house, 2, seed=2, mavlink=False, camera=None, noise="none", frame="world")
    for i, v in enumerate(sim.vehicles):
        s = sim.estimated_state(v)
        p, _ = sim.true_pose(i)
        np.testing.assert_allclose(s.pos, p, atol=1e-9)
        yaw_ned = euler_zyx(enu_flu_to_ned_frd(s.rot))[2]
        assert math.isclose(math.cos(yaw_ned), math.cos(math.pi / 2 - v.true_start_pose[3]), abs_tol=1e-6)


def test_drift_is_seeded_and_slow(house):
    def drift_after(seed):
        sim = Simulation(house, 2, seed=seed, mavlink=False, camera=None, noise="default")
        return [v.odometry.drift(60.0)[1] for v in sim.vehicles]

    a, b, c = drift_after(4), drift_after(4), drift_after(5)
    np.testing.assert_array_equal(a[0], b[0])
    assert not np.allclose(a[0], c[0])
    assert not np.allclose(a[0], a[1])  # each vehicle drifts its own way
    assert 0.0 < np.linalg.norm(a[0]) < 2.0  # metres after a minute


def test_drift_runs_only_while_armed(house):
    """Disarmed on the ground the estimate holds (zero-velocity updates, as PX4's EKF2 when landed);
    armed it drifts, and the drift of past times does not change."""
    sim = Simulation(house, 1, seed=4, mavlink=False, camera=None, noise="default")
    odo = sim.vehicles[0].odometry
    sim.step(5.0)  # disarmed
    assert odo.drift_time(sim.time) == 0.0 and not np.any(odo.drift(sim.time)[1])
    t_arm = sim.time
    sim.vehicles[0].fc.armed = True
    sim.step(4.0)
    assert abs(odo.drift_time(sim.time) - (sim.time - t_arm)) < 0.05
    moved = odo.drift(sim.time)[1].copy()
    np.testing.assert_allclose(moved, odo.drift_vel * odo.drift_time(sim.time))
    t_land = sim.time
    sim.vehicles[0].fc.armed = False
    sim.step(3.0)
    np.testing.assert_allclose(odo.drift(sim.time)[1], odo.drift(t_land)[1], atol=1e-12)
    assert odo.drift_time(t_arm) == 0.0 and odo.drift_time(2.0) == 0.0


def test_reported_noise_is_seeded():
    from firmware_sim.odometry import OdometryModel

    def sample(seed):
        m = OdometryModel((0, 0, 0), 0.0, NoiseConfig(), np.random.default_rng(seed))
        return m.noisy(np.zeros(3), np.eye(3), np.zeros(3))[0]

    np.testing.assert_array_equal(sample(1), sample(1))
    assert not np.allclose(sample(1), sample(2))


@pytest.mark.parametrize("name", ["small_house", "bookstore"])
def test_builtin_route_flies_without_collision(name):
    world = build_world(name, seed=0)
    sim = Simulation(world, 2, seed=1, mavlink=False, camera=None, route="builtin")
    for _ in range(200):
        sim.step(1.0)
        if all(sim.route_finished(i) for i in range(2)):
            break
    for i in range(2):
        assert sim.route_finished(i), (i, sim.vehicle(i).fc.mission_index, len(sim.vehicle(i).fc.mission))
        traj = sim.trajectory(i)
        assert traj[:, 3].max() > 0.9  # it flew
        rot_z = [quat_to_mat(q)[2, 2] for q in traj[:, 4:8]]
        assert min(rot_z) > math.cos(math.radians(40))  # never tumbled against a wall
        end = traj[-1, 1:3]
        assert np.linalg.norm(end - np.array(sim.vehicle(i).true_start_pose[:2])) < 1.0


def test_same_seed_same_flight(house):
    def fly(seed):
        sim = Simulation(house, 2, seed=seed, mavlink=False, camera=None, route="builtin")
        sim.step(8.0)
        return sim.trajectory(0), sim.trajectory(1)

    a, b, c = fly(11), fly(11), fly(12)
    np.testing.assert_array_equal(a[0], b[0])
    np.testing.assert_array_equal(a[1], b[1])
    assert not np.array_equal(a[0], c[0])  # another seed drifts differently, so flies differently


def test_vehicle_handles_expose_truth(house):
    sim = Simulation(house, 2, seed=0, mavlink=False, camera=None)
    sim.step(0.2)
    p, q = sim.vehicle(1).true_pose()
    np.testing.assert_allclose(p[:2], sim.vehicle(1).true_start_pose[:2], atol=1e-3)
    assert sim.vehicle(1).true_trajectory().shape[1] == 8
    assert sim.vehicle(1).mavlink_endpoint is None


def test_preflight_auto_disarm_and_hold_modes(house):
    from firmware_sim.flight import MAIN_POSCTL

    sim = Simulation(house, 1, seed=0, mavlink=False, camera=None, noise="none")
    v = sim.vehicle(0)
    sim.step(0.1)
    v.fc.arm(sim.time)
    sim.step(9.0)
    assert v.fc.armed  # still within COM_DISARM_PRFLT
    sim.step(2.0)
    assert not v.fc.armed  # armed on the ground for > 10 s without taking off
    v.fc.arm(sim.time)
    v.fc.takeoff(sim.time, 1.0)
    sim.step(4.0)
    assert v.fc.set_mode(MAIN_POSCTL, 0, sim.time) == 0  # no sticks: holds position
    p0 = sim.true_pose(0)[0]
    sim.step(3.0)
    assert np.linalg.norm(sim.true_pose(0)[0] - p0) < 0.05
    assert v.fc.set_mode(42, 0, sim.time) == 3


def test_crash_disarms(house):
    sim = Simulation(house, 1, seed=0, mavlink=False, camera=None, noise="none")
    v = sim.vehicle(0)
    sim.step(0.1)
    v.fc.arm(sim.time)
    v.fc.takeoff(sim.time, 1.5)
    sim.step(3.0)
    with sim.lock:  # a violent knock: 30 rad/s of roll
        sim.data.qvel[v.qvel_adr + 3] = 30.0
    sim.step(3.0)
    assert not v.fc.armed
    assert any("Crash" in text for _, text in v.fc.messages)
    assert sim.true_pose(0)[0][2] < 0.3  # it fell


@pytest.mark.slow
@pytest.mark.cpu_bound
@pytest.mark.parametrize("name", ["maze", "hospital"])
def test_long_builtin_routes_fly_clean(name):
    world = build_world(name, seed=2)
    sim = Simulation(world, 2, seed=2, mavlink=False, camera=None, route="builtin")
    for _ in range(300):
        sim.step(1.0)
        if all(sim.route_finished(i) for i in range(2)):
            break
    for i in range(2):
        assert sim.route_finished(i), (name, i)
        tilt = [quat_to_mat(q)[2, 2] for q in sim.trajectory(i)[:, 4:8]]
        assert min(tilt) > math.cos(math.radians(25))  # no knocks against door frames or walls

"""Collision prevention of the emulated FC (CP_DIST set by PARAM_SET, OBSTACLE_DISTANCE over MAVLink on
loopback) and the contacts the emulator records: a wall fed as OBSTACLE_DISTANCE stops a 1 m/s
offboard velocity command at least 0.5 m short; without CP_DIST the vehicle hits it."""

from __future__ import annotations

import math
import socket

import numpy as np
import pytest
from pymavlink.dialects.v20 import common as mav

from firmware_sim.collision import BINS, NO_DATA, bins_from_message, constrain_velocity
from firmware_sim.flight import MAIN_OFFBOARD, Setpoint
from firmware_sim.frames import quat_to_mat, yaw_of
from firmware_sim.shapes import box_from_corners
from firmware_sim.simulation import Simulation
from firmware_sim.worlds import World
from tests.loopback_fc import free_port

WALL_X = 8.0
"""The wall's face toward the vehicle (world x, metres)."""
MAX_CM = 1000
SENDER = mav.MAVLink(None, 245, 190)


def wall_world() -> World:
    shapes = [box_from_corners("floor_0", (0, 0, -0.1), (12, 6, 0)),
              box_from_corners("wall_1", (WALL_X, 0, 0), (WALL_X + 0.2, 6, 3))]
    loop = np.array([[1.0, 1.0], [6.0, 1.0], [6.0, 5.0], [1.0, 5.0]])
    return World("wall", 0, shapes, np.array([-0.2, -0.2, -0.2]), np.array([12.2, 6.2, 3.2]), loop)


def obstacle_distance(sim: Simulation, i: int = 0, blind: bool = False):
    """What a perfect 360-degree sensor on vehicle i reports of the wall (body FRD, 5-degree sectors)."""
    p, q = sim.true_pose(i)
    yaw = yaw_of(quat_to_mat(q))
    out = []
    for b in range(BINS):
        theta = yaw - math.radians(5.0 * b)
        d = (WALL_X - p[0]) / math.cos(theta) if math.cos(theta) > 1e-6 else math.inf
        hit = d <= MAX_CM / 100 and 0 <= p[1] + d * math.sin(theta) <= 6
        out.append(NO_DATA if blind else int(d * 100) if hit else MAX_CM + 1)
    return SENDER.obstacle_distance_encode(0, mav.MAV_DISTANCE_SENSOR_LASER, out, 5, 20, MAX_CM, 5.0, 0.0,
                                           mav.MAV_FRAME_BODY_FRD)


def param_set(sock, port: int, name: str, value: float) -> None:
    sock.sendto(SENDER.param_set_encode(1, 1, name.encode(), value, mav.MAV_PARAM_TYPE_REAL32).pack(SENDER),
                ("127.0.0.1", port))


def fly_at_the_wall(cp_dist: float | None, send_obstacles: bool = True, seconds: float = 9.0):
    """Take off to 1.5 m 5 m from the wall, then command 1 m/s toward it in offboard; OBSTACLE_DISTANCE
    at 10 Hz (sim time) if asked. Returns the simulation (stopped) and the closest approach."""
    sim = Simulation(wall_world(), 1, seed=0, camera=None, noise="none", frame="world",
                     start_poses=[(3.0, 3.0, 0.0, 0.0)], mavlink_base_port=free_port())
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    port = sim.vehicle(0).link.bound_port
    fc = sim.vehicle(0).fc
    try:
        if cp_dist is not None:
            param_set(sock, port, "CP_DIST", cp_dist)
        sim.step(0.1)
        assert fc.params["CP_DIST"] == (cp_dist if cp_dist is not None else -1.0)
        fc.arm(sim.time)
        fc.takeoff(sim.time, 1.5)
        sim.step(4.0)
        forward = Setpoint(vel=np.array([1.0, 0.0, 0.0]), yaw=0.0)
        fc.set_offboard_setpoint(forward)
        assert fc.set_mode(MAIN_OFFBOARD, 0, sim.time) == 0
        closest = math.inf
        for k in range(int(seconds / 0.05)):
            fc.set_offboard_setpoint(forward)
            if send_obstacles and k % 2 == 0:
                sock.sendto(obstacle_distance(sim).pack(SENDER), ("127.0.0.1", port))
            sim.step(0.05)
            closest = min(closest, WALL_X - sim.true_pose(0)[0][0])
        return sim, closest
    finally:
        sock.close()
        sim.stop()


def test_a_wall_fed_as_obstacle_distance_stops_the_vehicle_short_of_it():
    sim, closest = fly_at_the_wall(cp_dist=1.0)
    v = sim.vehicle(0)
    gap = closest - v.sim.airframe.half_extent[0]  # from the arms' reach to the wall
    assert gap >= 0.5, closest
    assert WALL_X - sim.true_pose(0)[0][0] < 1.5  # it did fly most of the way (not held at the start)
    assert v.contact_count == 0 and sim.contacts(0) == []
    assert v.fc.cp_cut_steps > 0 and v.link.stats["obstacle_distance"] >= 80


def test_without_collision_prevention_the_emulator_records_the_contact():
    sim, closest = fly_at_the_wall(cp_dist=None)
    v = sim.vehicle(0)
    assert v.contact_count >= 1, closest
    first = sim.contacts(0)[0]
    assert first.geom == "wall_1" and first.vehicle == 0 and first.speed_m_s > 0.3
    assert first.position[0] > WALL_X - 0.5 and v.fc.cp_cut_steps == 0


def test_without_obstacle_data_the_vehicle_does_not_move_toward_unknown():
    sim, closest = fly_at_the_wall(cp_dist=1.0, send_obstacles=False, seconds=3.0)
    assert closest > WALL_X - 3.0 - 0.3  # still near its start, 5 m from the wall
    assert sim.vehicle(0).contact_count == 0


def test_bins_from_message_frames_and_increments():
    sectors = [150] + [NO_DATA] * 17 + [MAX_CM + 1] * 18 + [5] * 36  # 36 of 10 degrees; the rest unused
    m = SENDER.obstacle_distance_encode(0, 0, sectors, 10, 20, MAX_CM, 10.0, 0.0, mav.MAV_FRAME_BODY_FRD)
    b = bins_from_message(m, yaw_ned=1.0, t=2.0)
    # 10-degree sectors centred on 0, 10, ...: bin 355 deg falls in sector 0, bin 5 deg on sector 1's edge
    assert b.distances_m[0] == 1.5 and b.distances_m[71] == 1.5 and math.isnan(b.distances_m[1])
    assert math.isnan(b.distances_m[10]) and b.distances_m[40] == math.inf and b.t == 2.0
    assert not np.any(b.distances_m == 0.2)  # elements past 360 degrees are not read
    north = SENDER.obstacle_distance_encode(0, 0, [150] + [MAX_CM + 1] * 71, 5, 20, MAX_CM, 5.0, 0.0,
                                            mav.MAV_FRAME_LOCAL_NED)
    east = bins_from_message(north, yaw_ned=math.radians(90.0), t=0.0)  # facing east: north is left
    assert east.distances_m[54] == 1.5 and np.isinf(east.distances_m[0])
    for bad in (mav.MAV_FRAME_LOCAL_ENU,):
        m.frame = bad
        assert bins_from_message(m, 0.0, 0.0) is None


@pytest.mark.parametrize("cp_dist,distance,expect_cut", [(1.0, 1.0, True), (1.0, 5.0, False)])
def test_constrain_velocity_cuts_only_toward_near_sectors(cp_dist, distance, expect_cut):
    m = SENDER.obstacle_distance_encode(0, 0, [int(distance * 100)] + [MAX_CM + 1] * 71, 5, 20, MAX_CM, 5.0,
                                        0.0, mav.MAV_FRAME_BODY_FRD)
    bins = bins_from_message(m, 0.0, 0.0)
    v, cut = constrain_velocity([1.0, 0.5], [0.0, 0.0], 0.0, bins, 0.1, cp_dist, 0.4, False)
    assert cut == expect_cut
    if expect_cut:
        assert abs(v[0]) < 1e-9 and v[1] == pytest.approx(0.5)  # sideways motion stays
    stale, _ = constrain_velocity([1.0, 0.5], [0.0, 0.0], 0.0, bins, 0.7, cp_dist, 0.4, False)
    assert np.allclose(stale, 0.0, atol=1e-9)  # data older than 0.5 s: no data in every direction

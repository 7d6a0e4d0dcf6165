"""MAVLink endpoint with pymavlink: identity, streams, intervals, timesync, params, commands, missions."""

from __future__ import annotations

import math
import time

import numpy as np
import pytest
from pymavlink.dialects.v20 import common as mav

from firmware_sim.flight import MAIN_AUTO, MAIN_OFFBOARD, SUB_LOITER
from firmware_sim.odometry import EARTH_RADIUS_M
from firmware_sim.simulation import Simulation
from firmware_sim.worlds import build_world

from .mavlink_client import Client

REQUIRED_STREAMS = {
    "HEARTBEAT",
    "SYS_STATUS",
    "ATTITUDE",
    "ATTITUDE_QUATERNION",
    "LOCAL_POSITION_NED",
    "ODOMETRY",
    "GLOBAL_POSITION_INT",
    "HOME_POSITION",
    "EXTENDED_SYS_STATE",
}


@pytest.fixture(scope="module")
def house():
    return build_world("small_house", seed=0)


@pytest.fixture
def sim_and_client(house, port_block):
    sim = Simulation(house, 2, seed=3, speed=4.0, camera=None, mavlink_base_port=port_block)
    clients = [Client(port_block, 1), Client(port_block + 1, 2)]
    sim.start()
    for c in clients:  # udpin learns the vehicle's address from its first packet
        assert c.wait("HEARTBEAT") is not None
    yield sim, clients
    sim.stop()
    for c in clients:
        c.conn.close()


def test_identity_and_streams(sim_and_client):
    sim, (c0, c1) = sim_and_client
    hb = c0.wait("HEARTBEAT")
    assert hb is not None and hb.get_srcComponent() == 1
    assert hb.autopilot == mav.MAV_AUTOPILOT_PX4 and hb.type == mav.MAV_TYPE_QUADROTOR
    hb1 = c1.wait("HEARTBEAT")
    assert hb1 is not None and hb1.get_srcSystem() == 2
    seen = {m.get_type() for m in c0.collect(1.5)}
    assert REQUIRED_STREAMS <= seen
    m = c0.wait("ATTITUDE")
    assert abs(m.time_boot_ms / 1000 - sim.time) < 0.5  # one simulated clock
    assert abs(m.yaw) < 0.05 and abs(m.roll) < 0.05 and abs(m.pitch) < 0.05  # start frame: heading = x
    q = c0.wait("ATTITUDE_QUATERNION")
    assert q.q1 > 0.99
    hb = c0.wait("EXTENDED_SYS_STATE")
    assert hb.landed_state == mav.MAV_LANDED_STATE_ON_GROUND
    odo = c0.wait("ODOMETRY")
    assert odo.frame_id == mav.MAV_FRAME_LOCAL_NED and odo.child_frame_id == mav.MAV_FRAME_BODY_FRD
    assert math.hypot(odo.x, odo.y) < 0.1  # reported frame starts at the start pose


def test_set_message_interval(sim_and_client):
    sim, (c0, _) = sim_and_client
    assert c0.command(mav.MAV_CMD_SET_MESSAGE_INTERVAL, mav.MAVLINK_MSG_ID_ATTITUDE, 100_000) == 0
    c0.collect(0.3)
    stamps = [m.time_boot_ms for m in c0.collect(1.5) if m.get_type() == "ATTITUDE"]
    rate = (len(stamps) - 1) / ((stamps[-1] - stamps[0]) / 1000)  # per simulated second
    assert 8 < rate < 12
    assert c0.command(mav.MAV_CMD_SET_MESSAGE_INTERVAL, mav.MAVLINK_MSG_ID_ATTITUDE, -1) == 0
    c0.collect(0.3)
    assert not [m for m in c0.collect(1.0) if m.get_type() == "ATTITUDE"]
    assert c0.command(mav.MAV_CMD_SET_MESSAGE_INTERVAL, 9999, 100_000) == mav.MAV_RESULT_UNSUPPORTED
    assert c0.command(mav.MAV_CMD_SET_MESSAGE_INTERVAL, mav.MAVLINK_MSG_ID_ATTITUDE, 0) == 0
    assert c0.wait("ATTITUDE", timeout=2) is not None


def test_timesync_version_and_params(sim_and_client):
    _, (c0, _) = sim_and_client
    c0.wait("HEARTBEAT")
    c0.mav.timesync_send(0, 123456789)
    ts = c0.wait("TIMESYNC", lambda m: m.ts1 == 123456789)
    assert ts is not None and ts.tc1 > 0
    assert c0.command(mav.MAV_CMD_REQUEST_MESSAGE, mav.MAVLINK_MSG_ID_AUTOPILOT_VERSION) == 0
    ver = c0.wait("AUTOPILOT_VERSION")
    assert ver.capabilities & mav.MAV_PROTOCOL_CAPABILITY_MISSION_INT
    c0.mav.param_request_list_send(1, 1)
    params = {}
    deadline = time.monotonic() + 5
    while time.monotonic() < deadline:
        p = c0.wait("PARAM_VALUE", timeout=1)
        if p is None:
            break
        params[p.param_id] = p
        if len(params) == p.param_count:
            break
    assert {"MIS_TAKEOFF_ALT", "MPC_XY_CRUISE", "NAV_ACC_RAD", "MAV_SYS_ID"} <= set(params)
    assert params["MIS_TAKEOFF_ALT"].param_value == pytest.approx(2.5)
    sysid = params["MAV_SYS_ID"]
    assert sysid.param_type == mav.MAV_PARAM_TYPE_INT32
    assert np.frombuffer(np.float32(sysid.param_value).tobytes(), "<i4")[0] == 1  # PX4 bytewise ints
    c0.mav.param_set_send(1, 1, b"MIS_TAKEOFF_ALT", 1.5, mav.MAV_PARAM_TYPE_REAL32)
    echo = c0.wait("PARAM_VALUE", lambda m: m.param_id == "MIS_TAKEOFF_ALT")
    assert echo.param_value == pytest.approx(1.5)
    c0.mav.param_request_read_send(1, 1, b"MIS_TAKEOFF_ALT", -1)
    assert c0.wait("PARAM_VALUE", lambda m: m.param_id == "MIS_TAKEOFF_ALT").param_value == pytest.approx(1.5)


def test_command_results(sim_and_client):
    sim, (c0, _) = sim_and_client
    c0.wait("HEARTBEAT")
    assert c0.command(31337) == mav.MAV_RESULT_UNSUPPORTED
    assert c0.command(mav.MAV_CMD_NAV_TAKEOFF, *[math.nan] * 7) == mav.MAV_RESULT_DENIED  # disarmed
    assert c0.command(mav.MAV_CMD_COMPONENT_ARM_DISARM, math.nan) == mav.MAV_RESULT_DENIED
    assert c0.set_mode(99) == mav.MAV_RESULT_UNSUPPORTED
    assert c0.set_mode(MAIN_OFFBOARD) == mav.MAV_RESULT_TEMPORARILY_REJECTED  # no setpoint stream
    assert c0.command(mav.MAV_CMD_DO_CHANGE_SPEED, 1, math.inf) == mav.MAV_RESULT_DENIED
    assert c0.command(mav.MAV_CMD_MISSION_START) == mav.MAV_RESULT_DENIED  # disarmed, no mission
    assert c0.command(mav.MAV_CMD_COMPONENT_ARM_DISARM, 1) == 0
    hb = c0.wait("HEARTBEAT", lambda m: m.base_mode & mav.MAV_MODE_FLAG_SAFETY_ARMED)
    assert hb is not None
    assert c0.command(mav.MAV_CMD_COMPONENT_ARM_DISARM, 0) == 0
    assert sim.vehicle(0).fc.armed is False


def test_arm_takeoff_offboard_land(sim_and_client):
    sim, (c0, _) = sim_and_client
    c0.wait("HEARTBEAT")
    c0.mav.param_set_send(1, 1, b"MIS_TAKEOFF_ALT", 1.5, mav.MAV_PARAM_TYPE_REAL32)
    assert c0.wait("PARAM_VALUE", lambda m: m.param_id == "MIS_TAKEOFF_ALT") is not None
    assert c0.command(mav.MAV_CMD_COMPONENT_ARM_DISARM, 1) == 0
    assert c0.command(mav.MAV_CMD_NAV_TAKEOFF, *[math.nan] * 7) == 0
    assert c0.wait("LOCAL_POSITION_NED", lambda m: m.z < -1.4, timeout=10) is not None
    start, _ = sim.true_pose(0)
    # Offboard: stream setpoints first, then switch; fly 1.5 m forward (local NED x = initial heading).
    deadline = time.monotonic() + 6
    switched, acks = False, []
    while time.monotonic() < deadline:
        c0.mav.set_position_target_local_ned_send(
            0, 1, 1, mav.MAV_FRAME_LOCAL_NED, 0b0000_1111_1111_1000, 1.5, 0.0, -1.5, 0, 0, 0, 0, 0, 0, 0, 0
        )
        if not switched and time.monotonic() > deadline - 5.5:
            c0.mav.command_long_send(1, 1, mav.MAV_CMD_DO_SET_MODE, 0, 1, MAIN_OFFBOARD, 0, 0, 0, 0, 0)
            switched = True
        acks += [
            m for m in c0.drain() if m.get_type() == "COMMAND_ACK" and m.command == mav.MAV_CMD_DO_SET_MODE
        ]
        time.sleep(0.05)
    assert [a.result for a in acks] == [mav.MAV_RESULT_ACCEPTED]
    assert sim.vehicle(0).fc.main_mode == MAIN_OFFBOARD
    p, _ = sim.true_pose(0)
    h = sim.vehicle(0).true_start_pose[3]
    np.testing.assert_allclose(p[:2] - start[:2], [1.5 * math.cos(h), 1.5 * math.sin(h)], atol=0.2)
    # Setpoints stop: PX4-like failsafe to hold.
    time.sleep(1.0)
    assert (sim.vehicle(0).fc.main_mode, sim.vehicle(0).fc.sub_mode) == (MAIN_AUTO, SUB_LOITER)
    assert c0.command(mav.MAV_CMD_NAV_LAND) == 0
    state = c0.wait("EXTENDED_SYS_STATE", lambda m: m.landed_state == mav.MAV_LANDED_STATE_ON_GROUND, 15)
    assert state is not None
    assert c0.wait("HEARTBEAT", lambda m: not m.base_mode & mav.MAV_MODE_FLAG_SAFETY_ARMED) is not None
    assert sim.true_pose(0)[0][2] < 0.1


def test_mission_upload_start_and_reached(sim_and_client):
    sim, (c0, _) = sim_and_client
    home = c0.wait("HOME_POSITION")
    lat0, lon0 = home.latitude * 1e-7, home.longitude * 1e-7

    def lla(north: float, east: float) -> tuple[int, int]:
        lat = lat0 + math.degrees(north / EARTH_RADIUS_M)
        lon = lon0 + math.degrees(east / (EARTH_RADIUS_M * math.cos(math.radians(lat0))))
        return int(round(lat * 1e7)), int(round(lon * 1e7))

    # Vehicle 0 starts in the living room at (3, 2.5) heading ~east; world north is +y, east +x.
    rel = mav.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT
    wp1, wp2 = lla(0.0, 1.2), lla(1.0, 1.2)
    items = [
        {"frame": rel, "command": mav.MAV_CMD_NAV_TAKEOFF, "z": 1.2},
        {"frame": rel, "command": mav.MAV_CMD_NAV_WAYPOINT, "x": wp1[0], "y": wp1[1], "z": 1.2},
        {"frame": rel, "command": mav.MAV_CMD_NAV_WAYPOINT, "x": wp2[0], "y": wp2[1], "z": 1.0},
        {"frame": rel, "command": mav.MAV_CMD_NAV_LAND, "x": wp2[0], "y": wp2[1], "z": 0.0},
    ]
    assert c0.upload_mission(items) == mav.MAV_MISSION_ACCEPTED
    c0.mav.mission_request_list_send(1, 1, 0)
    assert c0.wait("MISSION_COUNT").count == 4
    assert c0.command(mav.MAV_CMD_COMPONENT_ARM_DISARM, 1) == 0
    assert c0.command(mav.MAV_CMD_MISSION_START, 0, 3) == 0
    reached = []
    deadline = time.monotonic() + 20
    while len(reached) < 4 and time.monotonic() < deadline:
        m = c0.wait("MISSION_ITEM_REACHED", timeout=1)
        if m is not None:
            reached.append(m.seq)
    assert reached == [0, 1, 2, 3]
    assert c0.wait("HEARTBEAT", lambda m: not m.base_mode & mav.MAV_MODE_FLAG_SAFETY_ARMED, 15) is not None
    p, _ = sim.true_pose(0)
    start = np.array(sim.vehicle(0).true_start_pose[:2])
    np.testing.assert_allclose(p[:2], start + [1.2, 1.0], atol=0.35)  # estimate drift + acceptance radius
    assert p[2] < 0.1


def test_reposition_and_return_to_launch(sim_and_client):
    sim, (c0, _) = sim_and_client
    home = c0.wait("HOME_POSITION")
    lat0, lon0, alt0 = home.latitude * 1e-7, home.longitude * 1e-7, home.altitude * 1e-3
    assert c0.command(mav.MAV_CMD_COMPONENT_ARM_DISARM, 1) == 0
    assert c0.command(mav.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, math.nan, math.nan, math.nan, alt0 + 1.2) == 0
    assert c0.wait("LOCAL_POSITION_NED", lambda m: m.z < -1.1, timeout=10) is not None
    start = np.array(sim.vehicle(0).true_start_pose[:2])
    lat = int(round((lat0 + math.degrees(1.0 / EARTH_RADIUS_M)) * 1e7))  # 1 m north = world +y
    c0.drain()
    c0.mav.command_int_send(
        1,
        1,
        mav.MAV_FRAME_GLOBAL,
        mav.MAV_CMD_DO_REPOSITION,
        0,
        0,
        -1,
        0,
        0,
        math.nan,
        lat,
        int(round(lon0 * 1e7)),
        alt0 + 1.2,
    )
    ack = c0.wait("COMMAND_ACK", lambda m: m.command == mav.MAV_CMD_DO_REPOSITION)
    assert ack is not None and ack.result == 0
    deadline = time.monotonic() + 8
    while time.monotonic() < deadline and np.linalg.norm(sim.true_pose(0)[0][:2] - start - [0, 1]) > 0.1:
        time.sleep(0.1)
    np.testing.assert_allclose(sim.true_pose(0)[0][:2], start + [0.0, 1.0], atol=0.15)
    assert c0.command(mav.MAV_CMD_NAV_RETURN_TO_LAUNCH) == 0
    assert c0.wait("HEARTBEAT", lambda m: not m.base_mode & mav.MAV_MODE_FLAG_SAFETY_ARMED, 20) is not None
    np.testing.assert_allclose(sim.true_pose(0)[0][:2], start, atol=0.35)


def test_offboard_body_velocity_with_unset_vertical(sim_and_client):
    sim, (c0, _) = sim_and_client
    assert c0.command(mav.MAV_CMD_COMPONENT_ARM_DISARM, 1) == 0
    assert c0.command(mav.MAV_CMD_NAV_TAKEOFF, *[math.nan] * 7) == 0
    assert c0.wait("LOCAL_POSITION_NED", lambda m: m.z < -2.3, timeout=10) is not None
    z0 = sim.true_pose(0)[0][2]
    start = sim.true_pose(0)[0][:2].copy()
    ignore_all_but_vxy = 0b0000_1101_1110_0111  # vx, vy used; vz, position, accel, yaw rate ignored
    deadline, acks = time.monotonic() + 4, []
    sent_mode = False
    while time.monotonic() < deadline:
        c0.mav.set_position_target_local_ned_send(
            0, 1, 1, mav.MAV_FRAME_BODY_NED, ignore_all_but_vxy, 0, 0, 0, 0.5, 0.0, math.nan, 0, 0, 0, 0.0, 0
        )
        if not sent_mode:
            c0.mav.command_long_send(1, 1, mav.MAV_CMD_DO_SET_MODE, 0, 1, MAIN_OFFBOARD, 0, 0, 0, 0, 0)
            sent_mode = True
        acks += [m.result for m in c0.drain() if m.get_type() == "COMMAND_ACK"]
        time.sleep(0.05)
    assert acks == [0]
    p = sim.true_pose(0)[0]
    h = sim.vehicle(0).true_start_pose[3]
    moved = p[:2] - start
    assert moved @ [math.cos(h), math.sin(h)] > 2.0  # forward at 0.5 m/s for ~16 simulated seconds
    assert abs(p[2] - z0) < 0.3  # unset vertical velocity: altitude held, not dropped


def test_legacy_float_mission_in_local_ned(sim_and_client):
    sim, (c0, _) = sim_and_client
    items = [  # (command, x, y, z) in the vehicle's local NED frame: x = initial heading, z down
        (mav.MAV_CMD_NAV_TAKEOFF, 0.0, 0.0, -1.0),
        (mav.MAV_CMD_NAV_WAYPOINT, 1.0, 0.0, -1.0),
        (mav.MAV_CMD_NAV_WAYPOINT, 1.0, 0.5, -1.2),
        (mav.MAV_CMD_NAV_LAND, 1.0, 0.5, 0.0),
    ]
    c0.drain()
    c0.mav.mission_count_send(1, 1, len(items), 0)
    deadline = time.monotonic() + 10
    ack = None
    while ack is None and time.monotonic() < deadline:
        m = c0.conn.recv_match(type=["MISSION_REQUEST_INT", "MISSION_ACK"], blocking=True, timeout=0.5)
        if m is None:
            continue
        if m.get_type() == "MISSION_ACK":
            ack = m
            break
        cmd, x, y, z = items[m.seq]
        c0.mav.mission_item_send(
            1, 1, m.seq, mav.MAV_FRAME_LOCAL_NED, cmd, 0, 1, 0, 0, 0, math.nan, x, y, z, 0
        )
    assert ack is not None and ack.type == mav.MAV_MISSION_ACCEPTED
    # Download it back: the same items (MISSION_ITEM_INT carries local x, y in 1e-4 m).
    c0.mav.mission_request_list_send(1, 1, 0)
    assert c0.wait("MISSION_COUNT").count == 4
    c0.mav.mission_request_int_send(1, 1, 2, 0)
    it = c0.wait("MISSION_ITEM_INT", lambda m: m.seq == 2)
    assert (it.x, it.y, it.z, it.frame) == (10000, 5000, pytest.approx(-1.2), mav.MAV_FRAME_LOCAL_NED)
    c0.mav.mission_ack_send(1, 1, mav.MAV_MISSION_ACCEPTED, 0)
    assert c0.command(mav.MAV_CMD_COMPONENT_ARM_DISARM, 1) == 0
    assert c0.set_mode(4, 4) == 0  # AUTO.MISSION by mode switch, as QGroundControl does
    assert c0.wait("HEARTBEAT", lambda m: not m.base_mode & mav.MAV_MODE_FLAG_SAFETY_ARMED, 25) is not None
    h = sim.vehicle(0).true_start_pose[3]
    fwd, right = np.array([math.cos(h), math.sin(h)]), np.array([math.sin(h), -math.cos(h)])
    d = sim.true_pose(0)[0][:2] - np.array(sim.vehicle(0).true_start_pose[:2])
    assert abs(d @ fwd - 1.0) < 0.35 and abs(d @ right - 0.5) < 0.35


def test_interval_query_yaw_speed_and_mission_housekeeping(sim_and_client):
    sim, (c0, _) = sim_and_client
    assert c0.command(mav.MAV_CMD_GET_MESSAGE_INTERVAL, mav.MAVLINK_MSG_ID_ODOMETRY) == 0
    iv = c0.wait("MESSAGE_INTERVAL", lambda m: m.message_id == mav.MAVLINK_MSG_ID_ODOMETRY)
    assert iv is not None and iv.interval_us == pytest.approx(33333, abs=2)
    # Mission housekeeping: upload, jump, clear.
    rel = mav.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT
    home = c0.wait("HOME_POSITION")
    wp = {
        "frame": rel,
        "command": mav.MAV_CMD_NAV_WAYPOINT,
        "x": home.latitude,
        "y": home.longitude,
        "z": 1.0,
    }
    assert c0.upload_mission([wp, wp, wp]) == mav.MAV_MISSION_ACCEPTED
    c0.mav.mission_set_current_send(1, 1, 2)
    assert c0.wait("MISSION_CURRENT", lambda m: m.seq == 2 and m.total == 3) is not None
    c0.mav.mission_clear_all_send(1, 1, 0)
    assert c0.wait("MISSION_ACK").type == mav.MAV_MISSION_ACCEPTED
    assert sim.vehicle(0).fc.mission == []
    # Heading and speed commands in flight.
    assert c0.command(mav.MAV_CMD_COMPONENT_ARM_DISARM, 1) == 0
    assert c0.command(mav.MAV_CMD_NAV_TAKEOFF, *[math.nan] * 7) == 0
    assert c0.wait("LOCAL_POSITION_NED", lambda m: m.z < -2.3, timeout=10) is not None
    assert c0.command(mav.MAV_CMD_CONDITION_YAW, 90, 30, 1, 0) == 0  # absolute: local NED yaw 90 deg
    assert c0.wait("ATTITUDE", lambda m: abs(m.yaw - math.pi / 2) < 0.05, timeout=10) is not None
    assert c0.command(mav.MAV_CMD_DO_CHANGE_SPEED, 1, 0.5) == 0
    assert sim.vehicle(0).fc.cruise_speed == 0.5


def test_onboard_and_gcs_instances_share_the_vehicle_not_the_streams(house, port_block):
    """PX4 SITL's layout: each instance its own socket and stream rates; the vehicle's events
    (STATUSTEXT, arming) reach both."""
    sim = Simulation(house, 1, seed=3, speed=4.0, camera=None, mavlink_base_port=port_block,
                     gcs_port=port_block + 4)
    onboard, gcs = Client(port_block), Client(port_block + 4)
    sim.start()
    try:
        for c in (onboard, gcs):
            assert c.wait("HEARTBEAT") is not None
        assert "ODOMETRY" in {m.get_type() for m in onboard.collect(1.0)}
        assert "ODOMETRY" not in {m.get_type() for m in gcs.collect(1.0)}
        assert gcs.command(mav.MAV_CMD_SET_MESSAGE_INTERVAL, mav.MAVLINK_MSG_ID_ATTITUDE, -1) == 0
        gcs.drain()
        assert "ATTITUDE" not in {m.get_type() for m in gcs.collect(1.0)}  # off on the GCS instance
        assert "ATTITUDE" in {m.get_type() for m in onboard.collect(1.0)}  # still on the onboard one
        onboard.drain()
        assert gcs.command(mav.MAV_CMD_COMPONENT_ARM_DISARM, 1) == 0
        text = onboard.wait("STATUSTEXT", lambda m: "Armed" in m.text)
        assert text is not None  # an event of the vehicle, sent on every instance
        assert onboard.wait("HEARTBEAT", lambda m: m.base_mode & mav.MAV_MODE_FLAG_SAFETY_ARMED) is not None
    finally:
        sim.stop()
        onboard.conn.close()
        gcs.conn.close()

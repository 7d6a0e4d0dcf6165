"""The ArduCopter personality with pymavlink: identity and modes, streams and their rates, parameters,
the commands of a GUIDED flight, the mission protocol's home item."""

from __future__ import annotations

import time

import pytest
from pymavlink.dialects.v20 import common as mav

from firmware_sim import ardupilot as ap
from firmware_sim.simulation import Simulation
from firmware_sim.worlds import build_world

from .mavlink_client import Client


@pytest.fixture(scope="module")
def house():
    return build_world("small_house", seed=0)


@pytest.fixture
def copter(house, port_block):
    """One ArduCopter vehicle; a client on its onboard instance and one on its GCS instance."""
    sim = Simulation(house, 1, seed=3, speed=4.0, camera=None, mavlink_base_port=port_block,
                     gcs_port=port_block + 4, autopilot="ardupilot")
    onboard, gcs = Client(port_block), Client(port_block + 4)
    sim.start()
    for c in (onboard, gcs):
        assert c.wait("HEARTBEAT") is not None
    yield sim, onboard, gcs
    sim.stop()
    onboard.conn.close()
    gcs.conn.close()


def rate_hz(client: Client, mtype: str, seconds: float = 2.0) -> float:
    """Messages of a type per simulated second seen in a wall-time window (the sim runs at 4x)."""
    client.drain()
    msgs = [m for m in client.collect(seconds) if m.get_type() == mtype]
    if len(msgs) < 2:
        return 0.0
    return (len(msgs) - 1) / ((msgs[-1].time_boot_ms - msgs[0].time_boot_ms) / 1000)


def param(client: Client, name: str):
    """PARAM_VALUE of one parameter by name."""
    client.drain()
    client.mav.param_request_read_send(1, 1, name.encode(), -1)
    return client.wait("PARAM_VALUE", lambda m: m.param_id == name)


def test_identity_default_streams_and_no_odometry(copter):
    sim, onboard, gcs = copter
    hb = onboard.wait("HEARTBEAT")
    assert hb.autopilot == mav.MAV_AUTOPILOT_ARDUPILOTMEGA and hb.type == mav.MAV_TYPE_QUADROTOR
    assert hb.custom_mode == ap.STABILIZE and hb.system_status == mav.MAV_STATE_STANDBY
    assert hb.base_mode & mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
    seen = {m.get_type() for m in onboard.collect(1.5)}
    assert {"ATTITUDE", "LOCAL_POSITION_NED", "GLOBAL_POSITION_INT", "SYSTEM_TIME", "SYS_STATUS"} <= seen
    assert not seen & {"ODOMETRY", "ATTITUDE_QUATERNION"}  # only when asked for; ODOMETRY never
    assert rate_hz(onboard, "ATTITUDE") == pytest.approx(10.0, rel=0.15)  # SR0_EXTRA1
    assert rate_hz(gcs, "ATTITUDE") == pytest.approx(4.0, rel=0.2)  # SR1_EXTRA1: its own rates

    assert onboard.command(mav.MAV_CMD_SET_MESSAGE_INTERVAL, mav.MAVLINK_MSG_ID_ODOMETRY, 20000) == (
        mav.MAV_RESULT_FAILED)
    assert onboard.command(mav.MAV_CMD_SET_MESSAGE_INTERVAL, mav.MAVLINK_MSG_ID_ATTITUDE_QUATERNION,
                           20000) == mav.MAV_RESULT_ACCEPTED
    assert rate_hz(onboard, "ATTITUDE_QUATERNION") == pytest.approx(50.0, rel=0.15)
    assert not any(m.get_type() == "ATTITUDE_QUATERNION" for m in gcs.collect(0.5))


def test_request_data_stream_and_srx_parameters(copter):
    sim, onboard, gcs = copter
    gcs.mav.request_data_stream_send(1, 1, mav.MAV_DATA_STREAM_POSITION, 8, 1)
    time.sleep(0.3)
    assert rate_hz(gcs, "LOCAL_POSITION_NED") == pytest.approx(8.0, rel=0.15)
    assert param(gcs, "SR1_POSITION").param_value == 8.0  # the stream request is its parameter
    assert rate_hz(onboard, "LOCAL_POSITION_NED") == pytest.approx(10.0, rel=0.15)  # untouched

    gcs.drain()  # a full socket buffer (the client did not read for a while) would drop the echo
    gcs.mav.param_set_send(1, 1, b"SR0_EXTRA1", 2.0, mav.MAV_PARAM_TYPE_INT16)
    echo = gcs.wait("PARAM_VALUE", lambda m: m.param_id == "SR0_EXTRA1")
    assert echo.param_value == 2.0 and echo.param_type == mav.MAV_PARAM_TYPE_INT16
    time.sleep(0.3)
    assert rate_hz(onboard, "ATTITUDE") == pytest.approx(2.0, rel=0.25)
    gcs.mav.request_data_stream_send(1, 1, mav.MAV_DATA_STREAM_ALL, 0, 0)
    time.sleep(0.3)
    gcs.drain()
    assert {m.get_type() for m in gcs.collect(1.0)} <= {"HEARTBEAT", "PARAM_VALUE", "COMMAND_ACK"}


def test_parameters_by_arducopter_names(copter):
    sim, onboard, _ = copter
    sysid = param(onboard, "SYSID_THISMAV")
    assert sysid.param_value == 1.0 and sysid.param_type == mav.MAV_PARAM_TYPE_INT16  # C cast, not bytewise
    assert param(onboard, "WPNAV_SPEED").param_value == pytest.approx(200.0)  # cm/s
    onboard.drain()
    onboard.mav.param_set_send(1, 1, b"WPNAV_SPEED", 150.0, mav.MAV_PARAM_TYPE_REAL32)
    assert onboard.wait("PARAM_VALUE", lambda m: m.param_id == "WPNAV_SPEED").param_value == 150.0
    assert sim.vehicle(0).fc.params["MPC_XY_CRUISE"] == pytest.approx(1.5)  # the vehicle flies it
    onboard.drain()
    onboard.mav.param_set_send(1, 1, b"SYSID_THISMAV", 7.0, mav.MAV_PARAM_TYPE_INT16)
    assert onboard.wait("PARAM_VALUE", lambda m: m.param_id == "SYSID_THISMAV").param_value == 1.0
    onboard.drain()
    onboard.mav.param_request_list_send(1, 1)
    values = [m for m in onboard.collect(1.5) if m.get_type() == "PARAM_VALUE"]
    names = {m.param_id for m in values}
    assert {"SYSID_THISMAV", "SR0_POSITION", "SR1_EXTRA1", "LAND_SPEED"} <= names
    assert len(names) == values[0].param_count and "MAV_SYS_ID" not in names


def wait_mode(client: Client, mode: int, timeout: float = 5.0):
    return client.wait("HEARTBEAT", lambda m: m.custom_mode == mode, timeout)


def test_guided_takeoff_and_land(copter):
    sim, onboard, gcs = copter
    start = sim.true_pose(0)[0].copy()
    assert gcs.command(mav.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 2.0) == mav.MAV_RESULT_FAILED  # disarmed
    assert gcs.command(mav.MAV_CMD_DO_SET_MODE, 1, ap.AUTO) == mav.MAV_RESULT_ACCEPTED
    assert gcs.command(mav.MAV_CMD_COMPONENT_ARM_DISARM, 1) == mav.MAV_RESULT_FAILED  # not armable in AUTO
    assert gcs.command(mav.MAV_CMD_DO_SET_MODE, 1, ap.GUIDED) == mav.MAV_RESULT_ACCEPTED
    assert wait_mode(onboard, ap.GUIDED) is not None  # one vehicle: both instances report the mode
    assert gcs.command(mav.MAV_CMD_COMPONENT_ARM_DISARM, 1) == mav.MAV_RESULT_ACCEPTED
    assert gcs.command(mav.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 2.0) == mav.MAV_RESULT_ACCEPTED
    hb = gcs.wait("HEARTBEAT", lambda m: m.system_status == mav.MAV_STATE_ACTIVE)
    assert hb.custom_mode == ap.GUIDED and hb.base_mode & mav.MAV_MODE_FLAG_SAFETY_ARMED
    assert gcs.wait("GLOBAL_POSITION_INT", lambda m: m.relative_alt > 1900, timeout=10) is not None
    assert abs(sim.true_pose(0)[0][2] - start[2] - 2.0) < 0.3

    # A position target in GUIDED: 1 m along local north (NED), held until the next.
    lp = gcs.wait("LOCAL_POSITION_NED")
    gcs.mav.set_position_target_local_ned_send(0, 1, 1, mav.MAV_FRAME_LOCAL_NED, 0b110111111000,
                                               lp.x + 1.0, lp.y, lp.z, 0, 0, 0, 0, 0, 0, 0, 0)
    assert gcs.wait("LOCAL_POSITION_NED", lambda m: abs(m.x - lp.x - 1.0) < 0.1, timeout=10) is not None

    assert gcs.command(mav.MAV_CMD_NAV_LAND) == mav.MAV_RESULT_ACCEPTED
    assert wait_mode(gcs, ap.LAND) is not None
    hb = gcs.wait("HEARTBEAT", lambda m: not m.base_mode & mav.MAV_MODE_FLAG_SAFETY_ARMED, timeout=15)
    assert hb is not None and hb.custom_mode == ap.LAND  # disarmed on touchdown, still in LAND
    assert sim.true_pose(0)[0][2] < start[2] + 0.1


def test_mission_keeps_home_as_item_zero(copter):
    sim, onboard, gcs = copter
    home = gcs.wait("GLOBAL_POSITION_INT")
    gcs.mav.mission_request_list_send(1, 1, 0)
    assert gcs.wait("MISSION_COUNT").count == 1  # nothing uploaded: home only
    gcs.mav.mission_request_int_send(1, 1, 0, 0)
    item = gcs.wait("MISSION_ITEM_INT")
    assert item.seq == 0 and abs(item.x - home.lat) < 20 and abs(item.y - home.lon) < 20
    rel = mav.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT
    items = [dict(frame=rel, command=mav.MAV_CMD_NAV_WAYPOINT, x=0, y=0, z=0),  # home's slot
             dict(frame=rel, command=mav.MAV_CMD_NAV_TAKEOFF, z=1.5),
             dict(frame=rel, command=mav.MAV_CMD_NAV_LAND, x=home.lat, y=home.lon, z=0)]
    assert gcs.upload_mission(items) == mav.MAV_MISSION_ACCEPTED
    fc = sim.vehicle(0).fc
    assert [t.seq for t in fc.mission] == [1, 2]  # home is not flown
    assert gcs.command(mav.MAV_CMD_DO_SET_MODE, 1, ap.LOITER) == mav.MAV_RESULT_ACCEPTED
    assert gcs.command(mav.MAV_CMD_COMPONENT_ARM_DISARM, 1) == mav.MAV_RESULT_ACCEPTED
    assert gcs.command(mav.MAV_CMD_MISSION_START, 0, 0) == mav.MAV_RESULT_ACCEPTED
    assert wait_mode(gcs, ap.AUTO) is not None
    assert gcs.wait("MISSION_ITEM_REACHED", lambda m: m.seq == 1, timeout=10) is not None


def test_hostile_values_on_the_arducopter_handlers(copter):
    """Absurd stream requests, modes, parameters and commands: counted or refused, never a crash;
    the vehicle still flies a GUIDED takeoff afterwards."""
    import math

    from .test_hostile import NASTY, Paced, assert_alive

    sim, onboard, gcs = copter
    m = Paced(gcs.mav)
    for stream in (0, 1, 2, 6, 10, 12, 99, 255):
        for rate, start in ((65535, 1), (0, 1), (10, 0), (7, 2), (7, 255)):
            m.request_data_stream_send(1, 1, stream, rate, start)
    for mode in (0, 2, 3, 4, 5, 6, 9, 12, 99, 2**32 - 1):
        m.set_mode_send(1, 0, mode)
        m.set_mode_send(1, 1, mode)
    for name in (b"SR1_POSITION", b"SR0_EXTRA1", b"WPNAV_SPEED", b"LAND_SPEED", b"DISARM_DELAY", b"SR9_X"):
        for v in NASTY:
            m.param_set_send(1, 1, name, v, mav.MAV_PARAM_TYPE_INT16)
    for cmd in (mav.MAV_CMD_DO_SET_MODE, mav.MAV_CMD_NAV_TAKEOFF, mav.MAV_CMD_MISSION_START,
                mav.MAV_CMD_SET_MESSAGE_INTERVAL, mav.MAV_CMD_DO_REPOSITION,
                mav.MAV_CMD_COMPONENT_ARM_DISARM):
        for v in NASTY[:4]:
            m.command_long_send(1, 1, cmd, 0, v, v, v, v, v, v, v)
    m.command_long_send(1, 1, mav.MAV_CMD_COMPONENT_ARM_DISARM, 0, 0, 21196, 0, 0, 0, 0, 0)  # disarm again
    time.sleep(0.5)
    assert sim.vehicle(0).gcs_link.stats["rx_handler_errors"] == 0
    params = sim.vehicle(0).autopilot_state["params"]
    assert all(math.isfinite(params.get(n)[0]) for n in params.names)
    assert 0 < sim.vehicle(0).fc.params["MPC_XY_CRUISE"] and 0 <= params.get("SR1_POSITION")[0] <= 50
    assert sim.vehicle(0).fc.params["COM_DISARM_PRFLT"] > 0  # DISARM_DELAY: 0..127 s, 0 = never
    assert_alive(sim, gcs)
    gcs.mav.request_data_stream_send(1, 1, 0, 4, 1)
    assert gcs.command(mav.MAV_CMD_DO_SET_MODE, 1, ap.GUIDED) == mav.MAV_RESULT_ACCEPTED
    assert gcs.command(mav.MAV_CMD_COMPONENT_ARM_DISARM, 1) == mav.MAV_RESULT_ACCEPTED
    assert gcs.command(mav.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 1.5) == mav.MAV_RESULT_ACCEPTED
    assert gcs.wait("GLOBAL_POSITION_INT", lambda x: x.relative_alt > 1400, timeout=10) is not None

"""A real MAVLink client nobody here wrote (MAVSDK's C++ core, in-process) flies the emulator."""

from __future__ import annotations

import math
import time

import numpy as np
import pytest

mavsdk = pytest.importorskip("mavsdk")
from mavsdk import ComponentType, Configuration, ConnectionResult, Mavsdk  # noqa: E402
from mavsdk.plugins.action import Action  # noqa: E402
from mavsdk.plugins.offboard import Offboard, PositionNedYaw  # noqa: E402
from mavsdk.plugins.telemetry import Telemetry  # noqa: E402

from firmware_sim.simulation import Simulation  # noqa: E402
from firmware_sim.worlds import build_world  # noqa: E402


def poll(pred, timeout: float, what: str, period: float = 0.1):
    """Wait (wall time) until pred() is truthy; fail with a message otherwise."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = pred()
        if value:
            return value
        time.sleep(period)
    raise AssertionError(f"timed out waiting for {what}")


@pytest.mark.slow
def test_mavsdk_arm_takeoff_offboard_land(port_block):
    world = build_world("small_house", seed=0)
    sim = Simulation(world, 1, seed=7, speed=2.0, camera=None, mavlink_base_port=port_block)
    sim.start()
    m = Mavsdk(Configuration.create_with_component_type(ComponentType.COMPANION_COMPUTER))
    try:
        assert m.add_any_connection(f"udpin://127.0.0.1:{port_block}") == ConnectionResult.SUCCESS
        system = m.first_autopilot(10.0)
        assert system is not None and system.is_connected()
        telemetry, action, offboard = Telemetry(system), Action(system), Offboard(system)
        health = poll(  # home and global position may come a moment after armable under load
            lambda: (h := telemetry.health()).is_armable and h.is_local_position_ok
            and h.is_home_position_ok and h.is_global_position_ok and h,
            15,
            "health: armable with local, global and home positions",
        )
        assert health.is_home_position_ok and health.is_global_position_ok
        pv = poll(
            lambda: (p := telemetry.position_velocity_ned()) and math.isfinite(p.position.north_m) and p,
            5,
            "position telemetry",
        )
        assert math.hypot(pv.position.north_m, pv.position.east_m) < 0.2

        start, _ = sim.true_pose(0)
        action.set_takeoff_altitude(2.0)
        action.arm()
        poll(lambda: telemetry.armed(), 5, "armed")
        action.takeoff()
        poll(lambda: telemetry.position_velocity_ned().position.down_m < -1.9, 20, "takeoff to 2 m")
        assert abs(sim.true_pose(0)[0][2] - (start[2] + 2.0)) < 0.2
        assert telemetry.in_air()

        offboard.set_position_ned(PositionNedYaw(0.0, 0.0, -2.0, 0.0))
        offboard.start()
        poll(lambda: offboard.is_active(), 5, "offboard active")
        offboard.set_position_ned(PositionNedYaw(2.0, 0.5, -2.0, 0.0))
        poll(lambda: abs(telemetry.position_velocity_ned().position.north_m - 2.0) < 0.15, 20, "offboard leg")
        time.sleep(1.0)
        p, _ = sim.true_pose(0)
        heading = sim.vehicle(0).true_start_pose[3]
        forward = np.array([math.cos(heading), math.sin(heading)])
        right = np.array([math.sin(heading), -math.cos(heading)])
        d = p[:2] - start[:2]
        assert abs(d @ forward - 2.0) < 0.3 and abs(d @ right - 0.5) < 0.3  # NED x = heading, y = right
        offboard.stop()

        action.land()
        poll(lambda: not telemetry.armed(), 30, "landed and disarmed")
        assert sim.true_pose(0)[0][2] < 0.1
        assert not telemetry.in_air()
    finally:
        m.destroy()
        sim.stop()


@pytest.mark.slow
def test_mavsdk_mission(port_block):
    from mavsdk.plugins.mission import Mission, MissionItem, MissionPlan

    from firmware_sim.odometry import EARTH_RADIUS_M

    world = build_world("small_house", seed=0)
    sim = Simulation(world, 1, seed=7, speed=3.0, camera=None, mavlink_base_port=port_block)
    sim.start()
    m = Mavsdk(Configuration.create_with_component_type(ComponentType.COMPANION_COMPUTER))
    try:
        assert m.add_any_connection(f"udpin://127.0.0.1:{port_block}") == ConnectionResult.SUCCESS
        system = m.first_autopilot(10.0)
        telemetry, action, mission = Telemetry(system), Action(system), Mission(system)
        poll(lambda: telemetry.health().is_armable, 15, "armable")
        home = poll(lambda: (h := telemetry.home()) and math.isfinite(h.latitude_deg) and h, 5, "home")
        coslat = math.cos(math.radians(home.latitude_deg))

        def item(north: float, east: float) -> MissionItem:
            lat = home.latitude_deg + math.degrees(north / EARTH_RADIUS_M)
            lon = home.longitude_deg + math.degrees(east / (EARTH_RADIUS_M * coslat))
            nan = float("nan")
            return MissionItem(
                lat,
                lon,
                1.3,
                1.0,
                True,
                nan,
                nan,
                MissionItem.CameraAction.NONE,
                nan,
                nan,
                0.3,
                nan,
                nan,
                MissionItem.VehicleAction.NONE,
            )

        # Vehicle 0 starts at (3, 2.5) in the living room; world east is +x, north +y.
        mission.set_return_to_launch_after_mission(False)
        mission.upload_mission(MissionPlan([item(0.0, 1.5), item(1.0, 1.5), item(1.0, 0.5)]))
        assert len(mission.download_mission().mission_items) == 3
        action.arm()
        mission.start_mission()
        poll(lambda: mission.is_mission_finished(), 30, "mission finished")
        p, _ = sim.true_pose(0)
        x0, y0 = sim.vehicle(0).true_start_pose[:2]
        np.testing.assert_allclose(p[:2], [x0 + 0.5, y0 + 1.0], atol=0.4)
        assert abs(p[2] - 1.3 - sim.vehicle(0).true_start_pose[2]) < 0.3
        action.land()
        poll(lambda: not telemetry.armed(), 30, "landed and disarmed")
    finally:
        m.destroy()
        sim.stop()


@pytest.mark.slow
def test_mavsdk_on_the_gcs_instance_and_coopd_on_the_onboard_instance_at_once(port_block):
    """PX4 SITL's layout: a GCS (MAVSDK here) on the GCS port and coopd on the onboard port of the
    same vehicle, each with its own streams; coopd keeps its poses while MAVSDK flies."""
    from pymavlink.dialects.v20 import common as mav

    from coopd.vehicle import LinkConfig, VehicleLink

    gcs_port = port_block + 4
    world = build_world("small_house", seed=0)
    sim = Simulation(world, 1, seed=7, speed=2.0, camera=None, mavlink_base_port=port_block,
                     gcs_port=gcs_port)
    v = sim.vehicle(0)
    assert v.link.target[1] == port_block and v.gcs_link.target[1] == gcs_port
    assert v.gcs_link.bound_port != v.link.bound_port
    link = VehicleLink(LinkConfig(connection=f"udpin:127.0.0.1:{port_block}"))
    m = Mavsdk(Configuration.create_with_component_type(ComponentType.GROUND_STATION))
    link.start()
    sim.start()
    try:
        assert m.add_any_connection(f"udpin://127.0.0.1:{gcs_port}") == ConnectionResult.SUCCESS
        system = m.first_autopilot(10.0)
        assert system is not None and system.is_connected()
        telemetry, action = Telemetry(system), Action(system)
        poll(lambda: telemetry.health().is_armable, 15, "armable (GCS instance)")
        poll(lambda: not link.odometry_stale() and link.poses.latest() is not None, 10, "coopd poses")
        # Each instance keeps its own stream rates: coopd asked the onboard one for ODOMETRY at its
        # rate; the GCS instance never streams ODOMETRY.
        odometry_interval = 1.0 / link.config.odometry_rate_hz
        assert v.link.intervals[mav.MAVLINK_MSG_ID_ODOMETRY] == pytest.approx(odometry_interval)
        assert not v.gcs_link.intervals.get(mav.MAVLINK_MSG_ID_ODOMETRY)

        action.set_takeoff_altitude(2.0)
        action.arm()
        poll(lambda: telemetry.armed(), 5, "armed")
        action.takeoff()
        poll(lambda: telemetry.position_velocity_ned().position.down_m < -1.9, 20, "takeoff to 2 m")
        latest = link.poses.latest()
        assert abs(latest.position[2] - 2.0) < 0.3  # coopd's map-frame height saw the climb too
        action.land()
        poll(lambda: not telemetry.armed(), 30, "landed and disarmed")
        assert not link.odometry_stale()
        assert v.gcs_link.stats["tx"] > 0 and v.link.stats["tx"] > v.gcs_link.stats["tx"]
        assert v.link.stats["peer_heartbeats"] > 0 and v.gcs_link.stats["peer_heartbeats"] > 0
    finally:
        m.destroy()
        link.stop()
        sim.stop()

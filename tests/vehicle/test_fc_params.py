"""Reading from the FC's parameters whether it uses obstacle data (coopd.vehicle.fc_params)."""

import math
import struct

import pytest
from pymavlink.dialects.v20 import common as mav

from coopd.vehicle.fc_params import (
    ASK_PERIOD_S,
    ASKS_BEFORE_BACKOFF,
    RECHECK_PERIOD_S,
    ObstacleDemandWatch,
    obstacle_demand,
    param_value,
    watched_params,
)
from coopd.vehicle.link import LinkConfig, VehicleLink
from firmware_sim.simulation import Simulation
from firmware_sim.worlds import build_world
from tests.firmware_sim.mavlink_client import Client
from tests.loopback_fc import free_port
from tests.vehicle.sim_helpers import wait_until

PX4, ARDUPILOT = mav.MAV_AUTOPILOT_PX4, mav.MAV_AUTOPILOT_ARDUPILOTMEGA


def px4_int(value: int) -> float:
    """How PX4 puts an integer parameter in PARAM_VALUE's float (bytewise)."""
    return struct.unpack("<f", struct.pack("<i", value))[0]


def test_each_stack_has_its_own_parameters():
    assert watched_params(PX4) == ("CP_DIST",)
    assert watched_params(ARDUPILOT) == ("PRX1_TYPE", "PRX_TYPE")
    assert watched_params(mav.MAV_AUTOPILOT_GENERIC) == ()


def test_values_are_decoded_as_each_stack_encodes_them():
    assert param_value(1.5, mav.MAV_PARAM_TYPE_REAL32, PX4) == 1.5
    assert param_value(px4_int(2), mav.MAV_PARAM_TYPE_INT32, PX4) == 2.0  # bytewise, not 2.8e-45
    assert param_value(2.0, mav.MAV_PARAM_TYPE_INT8, ARDUPILOT) == 2.0  # a float cast
    assert param_value(math.nan, mav.MAV_PARAM_TYPE_REAL32, PX4) is None
    assert param_value(math.inf, mav.MAV_PARAM_TYPE_INT8, ARDUPILOT) is None


def test_the_demand_follows_the_settings():
    assert obstacle_demand(PX4, {})[0] is None
    assert obstacle_demand(PX4, {"CP_DIST": -1.0}) == (False, "CP_DIST = -1 m (collision prevention off)")
    assert obstacle_demand(PX4, {"CP_DIST": 0.0})[0] is False
    assert obstacle_demand(PX4, {"CP_DIST": 0.8}) == (True, "CP_DIST = 0.8 m")
    assert obstacle_demand(ARDUPILOT, {})[0] is None
    assert obstacle_demand(ARDUPILOT, {"PRX1_TYPE": 2.0}) == (True, "PRX1_TYPE = 2")
    assert obstacle_demand(ARDUPILOT, {"PRX_TYPE": 2.0})[0] is True  # before ArduPilot 4.3
    assert obstacle_demand(ARDUPILOT, {"PRX1_TYPE": 5.0})[0] is False  # another proximity sensor
    assert obstacle_demand(mav.MAV_AUTOPILOT_GENERIC, {"CP_DIST": 1.0})[0] is None


def test_the_watch_asks_until_answered_then_rechecks_slowly():
    w = ObstacleDemandWatch()
    assert w.due(0.0) == [] and w.demand()[0] is None  # no autopilot heard yet: nothing to ask
    w.follow(PX4)
    assert w.due(0.0) == ["CP_DIST"] and w.due(ASK_PERIOD_S / 2) == []
    assert w.due(ASK_PERIOD_S) == ["CP_DIST"]
    assert w.on_value("CP_DIST", 1.0, mav.MAV_PARAM_TYPE_REAL32)
    assert w.demand() == (True, "CP_DIST = 1 m")
    assert w.due(2 * ASK_PERIOD_S) == [] and w.due(ASK_PERIOD_S + RECHECK_PERIOD_S) == ["CP_DIST"]
    assert not w.on_value("SYS_AUTOSTART", 1.0, mav.MAV_PARAM_TYPE_REAL32)  # not ours: ignored
    assert w.on_value("CP_DIST", math.nan, mav.MAV_PARAM_TYPE_REAL32) and w.refused == 1
    assert w.demand() == (True, "CP_DIST = 1 m")  # a value that is no number changes nothing


def test_an_fc_that_never_answers_is_asked_less_often():
    w = ObstacleDemandWatch()
    w.follow(ARDUPILOT)
    t, asked = 0.0, 0
    while t < ASKS_BEFORE_BACKOFF * ASK_PERIOD_S + RECHECK_PERIOD_S:
        asked += len(w.due(t))
        t += 0.5
    assert asked == 2 * (ASKS_BEFORE_BACKOFF + 1)  # both names, five quick asks and one recheck each


def test_another_autopilot_forgets_what_was_said():
    w = ObstacleDemandWatch()
    w.follow(PX4)
    w.on_value("CP_DIST", 1.0, mav.MAV_PARAM_TYPE_REAL32)
    w.follow(PX4)  # the same one again: kept
    assert w.demand()[0] is True
    w.follow(ARDUPILOT)
    assert w.demand()[0] is None and sorted(w.due(100.0)) == ["PRX1_TYPE", "PRX_TYPE"]


@pytest.mark.parametrize("autopilot, name, on", [("px4", "CP_DIST", 1.0), ("ardupilot", "PRX1_TYPE", 2.0)])
def test_coopd_hears_a_ground_station_turn_obstacle_use_on(autopilot, name, on):
    """Against the emulated FC of each stack: coopd's link (the onboard instance) asks and learns the
    setting is off; a ground station (the GCS instance) sets it; the FC sends the new value on every
    instance, and coopd's demand turns on within a second, without asking again."""
    onboard, gcs_port = free_port(), free_port()
    sim = Simulation(build_world("small_house", 0), 1, seed=3, camera=None, mavlink_base_port=onboard,
                     gcs_port=gcs_port, autopilot=autopilot)
    link = VehicleLink(LinkConfig(connection=f"udpin:127.0.0.1:{onboard}", watch_obstacle_demand=True))
    gcs = Client(gcs_port)
    link.start()
    sim.start()
    demand = link.obstacle_demand.demand
    try:
        assert wait_until(lambda: demand()[0] is False, 10.0), demand()
        asked = link.counters["obstacle_params_asked"]
        assert gcs.wait("HEARTBEAT") is not None
        gcs.mav.param_set_send(1, 1, name.encode(), on, mav.MAV_PARAM_TYPE_REAL32)
        assert wait_until(lambda: demand()[0] is True, 5.0), demand()
        assert demand()[1].startswith(f"{name} = {on:g}")
        assert link.counters["obstacle_params_asked"] <= asked + 2  # heard, not asked (ArduPilot: 2 names)
    finally:
        link.stop()
        sim.stop()
        gcs.conn.close()

"""The ArduCopter personality of a vehicle's MAVLink instance: what a client of ArduPilot meets.

The same emulated vehicle (flight.FlightController) behind ArduPilot's MAVLink behaviour:
- HEARTBEAT from MAV_AUTOPILOT_ARDUPILOTMEGA with ArduCopter's custom mode numbers (STABILIZE 0,
  AUTO 3, GUIDED 4, LOITER 5, RTL 6, LAND 9); system_status STANDBY on the ground, ACTIVE in the air.
- Streams in ArduPilot's groups, at the rates of the SRn_* parameters (n = the instance: SR0_ the
  onboard/API instance, SR1_ the GCS one), changed by REQUEST_DATA_STREAM (a whole group) or
  MAV_CMD_SET_MESSAGE_INTERVAL (one message). ATTITUDE (Euler) and LOCAL_POSITION_NED flow by default;
  ATTITUDE_QUATERNION only when asked for. ArduPilot has no ODOMETRY output: asking for it fails
  (MAV_RESULT_FAILED), as on the real autopilot, so a client must build poses from
  LOCAL_POSITION_NED + ATTITUDE_QUATERNION.
- ArduCopter parameter names (SYSID_THISMAV, WPNAV_SPEED in cm/s, ...) with C-cast values and
  integer types, as ArduPilot sends them.
- GUIDED takeoff (MAV_CMD_NAV_TAKEOFF: armed, landed, in GUIDED; param7 = metres above home),
  position targets only in GUIDED, LAND / RTL as modes, arming refused in AUTO, LAND and RTL.
- The mission protocol with item 0 = home, as ArduPilot keeps it.
"""

from __future__ import annotations

import math

import numpy as np
from pymavlink.dialects.v20 import common as mav

from firmware_sim import flight
from firmware_sim.frames import euler_zyx
from firmware_sim.mavlink_link import COMMANDS, MavlinkLink, _param_name
from firmware_sim.mission_protocol import MissionItem, MissionServer

STABILIZE, ACRO, ALT_HOLD, AUTO, GUIDED, LOITER, RTL, CIRCLE, LAND = 0, 1, 2, 3, 4, 5, 6, 7, 9
POSHOLD, BRAKE = 16, 17
MODE_NAMES = {STABILIZE: "STABILIZE", AUTO: "AUTO", GUIDED: "GUIDED", LOITER: "LOITER", RTL: "RTL",
              LAND: "LAND", POSHOLD: "POSHOLD", BRAKE: "BRAKE"}
HOLDING_MODES = (GUIDED, LOITER, POSHOLD, BRAKE)
"""Modes in which the emulated vehicle holds its position (no pilot sticks to follow)."""
GROUND_ONLY_MODES = (STABILIZE, ACRO, ALT_HOLD)
"""Pilot modes: the emulator has no pilot, so it accepts them only on the ground (nothing to fly)."""
ARMABLE_MODES = (STABILIZE, ALT_HOLD, GUIDED, LOITER, POSHOLD, BRAKE)
GUIDED_ENABLED_MODES = (AUTO, GUIDED, LOITER, RTL, CIRCLE, POSHOLD, BRAKE)

# ArduPilot's stream groups (MAV_DATA_STREAM id, SRn_ suffix) and the messages of each we produce.
STREAMS = {
    mav.MAV_DATA_STREAM_RAW_SENSORS: ("RAW_SENS", ()),
    mav.MAV_DATA_STREAM_EXTENDED_STATUS: ("EXT_STAT", (mav.MAVLINK_MSG_ID_SYS_STATUS,
                                                       mav.MAVLINK_MSG_ID_MISSION_CURRENT,
                                                       mav.MAVLINK_MSG_ID_GPS_RAW_INT)),
    mav.MAV_DATA_STREAM_RC_CHANNELS: ("RC_CHAN", ()),
    mav.MAV_DATA_STREAM_RAW_CONTROLLER: ("RAW_CTRL", ()),
    mav.MAV_DATA_STREAM_POSITION: ("POSITION", (mav.MAVLINK_MSG_ID_GLOBAL_POSITION_INT,
                                                mav.MAVLINK_MSG_ID_LOCAL_POSITION_NED)),
    mav.MAV_DATA_STREAM_EXTRA1: ("EXTRA1", (mav.MAVLINK_MSG_ID_ATTITUDE,)),
    mav.MAV_DATA_STREAM_EXTRA2: ("EXTRA2", (mav.MAVLINK_MSG_ID_VFR_HUD,)),
    mav.MAV_DATA_STREAM_EXTRA3: ("EXTRA3", (mav.MAVLINK_MSG_ID_SYSTEM_TIME,
                                            mav.MAVLINK_MSG_ID_BATTERY_STATUS)),
}
PARAMS_STREAM_SUFFIXES = ("PARAMS", "ADSB")  # parameters exist; nothing the emulator streams
# Default SRn_ rates (Hz) per instance: 0 = onboard/API (what a companion computer needs), 1 = GCS.
DEFAULT_STREAM_HZ = {
    0: {"EXT_STAT": 2, "POSITION": 10, "EXTRA1": 10, "EXTRA2": 0, "EXTRA3": 2},
    1: {"EXT_STAT": 2, "POSITION": 3, "EXTRA1": 4, "EXTRA2": 4, "EXTRA3": 2},
}
MAX_STREAM_HZ = 50

# ArduCopter parameters backed by the flight controller's tuning (name: FC key, ArduPilot units per FC
# unit, MAVLink type).
FC_BACKED = {
    "WPNAV_SPEED": ("MPC_XY_CRUISE", 100.0, mav.MAV_PARAM_TYPE_REAL32),
    "WPNAV_SPEED_UP": ("MPC_Z_VEL_MAX_UP", 100.0, mav.MAV_PARAM_TYPE_REAL32),
    "WPNAV_RADIUS": ("NAV_ACC_RAD", 100.0, mav.MAV_PARAM_TYPE_REAL32),
    "LAND_SPEED": ("MPC_LAND_SPEED", 100.0, mav.MAV_PARAM_TYPE_INT16),
    "RTL_ALT": ("RTL_RETURN_ALT", 100.0, mav.MAV_PARAM_TYPE_INT32),
    "PILOT_TKOFF_ALT": ("MIS_TAKEOFF_ALT", 100.0, mav.MAV_PARAM_TYPE_REAL32),
}
NEVER_S = 1e9
"""DISARM_DELAY = 0 turns ArduCopter's disarm-on-the-ground off: the FC's delay becomes this."""
INT_RANGES = {
    mav.MAV_PARAM_TYPE_INT8: (-128, 127),
    mav.MAV_PARAM_TYPE_INT16: (-32768, 32767),
    mav.MAV_PARAM_TYPE_INT32: (-(2**31), 2**31 - 1),
}
RANGES = {"DISARM_DELAY": (0, 127)}
"""Documented ranges of own parameters (SRn_* are 0..MAX_STREAM_HZ); values outside are refused."""
READ_ONLY = {"SYSID_THISMAV", "FRAME_CLASS", "FRAME_TYPE"}
"""Changing these needs a reboot on ArduPilot; the emulator keeps them fixed and echoes the value."""
N_INSTANCES = 2

CAPABILITIES = (
    mav.MAV_PROTOCOL_CAPABILITY_MISSION_FLOAT
    | mav.MAV_PROTOCOL_CAPABILITY_PARAM_FLOAT
    | mav.MAV_PROTOCOL_CAPABILITY_MISSION_INT
    | mav.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
    | mav.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_C_CAST
    | mav.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_LOCAL_NED
    | mav.MAV_PROTOCOL_CAPABILITY_MAVLINK2
)
COPTER_VERSION = (4 << 24) | (5 << 16) | (7 << 8) | 255  # 4.5.7 official


class ArduCopterParams:
    """One vehicle's ArduCopter parameter table (shared by its instances): name -> (value, type)."""

    def __init__(self, vehicle) -> None:
        self.v = vehicle
        self.own: dict[str, tuple[float, int]] = {
            "SYSID_THISMAV": (float(vehicle.system_id), mav.MAV_PARAM_TYPE_INT16),
            "SYSID_MYGCS": (255.0, mav.MAV_PARAM_TYPE_INT16),
            "FRAME_CLASS": (1.0, mav.MAV_PARAM_TYPE_INT8),
            "FRAME_TYPE": (1.0, mav.MAV_PARAM_TYPE_INT8),
            "DISARM_DELAY": (10.0, mav.MAV_PARAM_TYPE_INT8),
            # proximity sensor 1's type (2: MAVLink, what a companion reads to know its OBSTACLE_DISTANCE
            # is used); reported and settable, but this personality does not avoid obstacles
            "PRX1_TYPE": (0.0, mav.MAV_PARAM_TYPE_INT8),
        }
        self._apply_disarm_delay()
        for n in range(N_INSTANCES):
            for name, _ in STREAMS.values():
                rate = DEFAULT_STREAM_HZ[n].get(name, 0)
                self.own[f"SR{n}_{name}"] = (float(rate), mav.MAV_PARAM_TYPE_INT16)
            for name in PARAMS_STREAM_SUFFIXES:
                self.own[f"SR{n}_{name}"] = (0.0, mav.MAV_PARAM_TYPE_INT16)
        self.names = sorted([*self.own, *FC_BACKED])

    def get(self, name: str) -> tuple[float, int]:
        """(value, MAV_PARAM_TYPE) of a known parameter."""
        if name in FC_BACKED:
            key, scale, ptype = FC_BACKED[name]
            value = self.v.fc.params[key] * scale
            return (float(round(value)) if ptype != mav.MAV_PARAM_TYPE_REAL32 else float(value)), ptype
        return self.own[name]

    def set(self, name: str, value: float) -> bool:
        """Set a known parameter (integers cast and clamped like ArduPilot); False if refused."""
        _, ptype = self.get(name)
        if not math.isfinite(value) or name in READ_ONLY:
            return False
        if ptype in INT_RANGES:
            lo, hi = INT_RANGES[ptype]
            value = float(min(max(int(value), lo), hi))
        if name in FC_BACKED:
            key, scale, _ = FC_BACKED[name]
            if value <= 0:
                return False  # a zero speed or radius would stall the emulated vehicle
            self.v.fc.params[key] = value / scale
            return True
        lo, hi = RANGES.get(name, (0, MAX_STREAM_HZ) if name.startswith("SR") else (-math.inf, math.inf))
        if not lo <= value <= hi:
            return False
        self.own[name] = (value, ptype)
        self._apply_disarm_delay()
        return True

    def _apply_disarm_delay(self) -> None:
        """The FC disarms on the ground after DISARM_DELAY seconds without a takeoff (0: never)."""
        delay = self.own["DISARM_DELAY"][0]
        self.v.fc.params["COM_DISARM_PRFLT"] = delay if delay > 0 else NEVER_S


class ArduPilotMissionServer(MissionServer):
    """ArduPilot keeps home as item 0 of the flight plan: downloads start with it, uploads' item 0
    is taken as home's slot and not flown."""

    def download_plan(self, mtype: int) -> list[MissionItem]:
        plan = self.plans[mtype]
        if mtype != mav.MAV_MISSION_TYPE_MISSION:
            return plan
        return [self.link.home_item(), *plan[1:]]


class ArduCopterLink(MavlinkLink):
    """One MAVLink instance of a vehicle with ArduCopter's behaviour (module docstring)."""

    def __init__(self, sim, vehicle, target, bind_port: int = 0, bind_host: str = "127.0.0.1",
                 rates: dict[int, float] | None = None, instance: int = 0):
        if not 0 <= instance < N_INSTANCES:
            raise ValueError(f"an ArduCopter vehicle has instances 0..{N_INSTANCES - 1}")
        state = vehicle.autopilot_state
        state.setdefault("mode", STABILIZE)
        self.params = state.setdefault("params", ArduCopterParams(vehicle))
        self.default_rates = self._stream_rates(instance) if rates is None else dict(rates)
        super().__init__(sim, vehicle, target, bind_port, bind_host, self.default_rates, instance)
        self.mission = ArduPilotMissionServer(self)
        del self.producers[mav.MAVLINK_MSG_ID_ODOMETRY]  # ArduPilot sends no ODOMETRY
        self.producers[mav.MAVLINK_MSG_ID_VFR_HUD] = self._vfr_hud

    def _stream_rates(self, instance: int) -> dict[int, float]:
        """Message rates (Hz) from this instance's SRn_ parameters; HEARTBEAT always at 1 Hz."""
        rates = {mav.MAVLINK_MSG_ID_HEARTBEAT: 1.0}
        for name, msgs in STREAMS.values():
            hz = self.params.get(f"SR{instance}_{name}")[0]
            rates.update(dict.fromkeys(msgs, hz))
        return rates

    def apply_stream_rate(self, stream_name: str, hz: float) -> None:
        """A stream group's rate changed: every message of the group follows (per-message intervals
        set earlier are replaced, as on ArduPilot)."""
        for name, msgs in STREAMS.values():
            if name != stream_name:
                continue
            for msg_id in msgs:
                self.default_rates[msg_id] = hz
                self.intervals[msg_id] = 1.0 / hz if hz > 0 else 0.0
                self.next_due[msg_id] = self.sim.time
        self._earliest_due = self.sim.time

    # ------------------------------------------------------------------ mode

    @property
    def mode(self) -> int:
        """The ArduCopter mode the vehicle is in, reconciled with what the flight controller did by
        itself (a finished landing, a mission's end)."""
        fc, state = self.v.fc, self.v.autopilot_state
        selected = state["mode"]
        if not fc.armed:
            return selected  # the FC's internal mode only matters while it flies
        if fc.main_mode == flight.MAIN_OFFBOARD:
            mode = GUIDED
        elif fc.sub_mode == flight.SUB_LAND:
            mode = LAND
        elif fc.sub_mode == flight.SUB_RTL:
            mode = RTL
        elif fc.sub_mode == flight.SUB_MISSION:
            mode = AUTO
        elif fc.sub_mode == flight.SUB_TAKEOFF:
            mode = selected if selected in (GUIDED, AUTO) else GUIDED
        elif selected in HOLDING_MODES or (selected in GROUND_ONLY_MODES and fc.landed):
            mode = selected
        else:
            mode = LOITER
        state["mode"] = mode
        return mode

    def set_mode(self, mode: int) -> int:
        """Enter an ArduCopter mode (DO_SET_MODE / SET_MODE); returns a MAV_RESULT."""
        fc, t, state = self.v.fc, self.sim.time, self.v.autopilot_state
        if mode in GROUND_ONLY_MODES:
            if fc.armed and not fc.landed:
                self._text(4, f"Mode {MODE_NAMES.get(mode, mode)} needs a pilot: refused in flight")
                return mav.MAV_RESULT_FAILED
            state["mode"] = mode
            return mav.MAV_RESULT_ACCEPTED
        if mode in HOLDING_MODES:
            taking_off = fc.main_mode == flight.MAIN_AUTO and fc.sub_mode == flight.SUB_TAKEOFF
            if fc.armed and not taking_off:
                fc.set_mode(flight.MAIN_AUTO, flight.SUB_LOITER, t)  # stop where it is
            state["mode"] = mode
            return mav.MAV_RESULT_ACCEPTED
        if mode == AUTO:
            if fc.armed and fc.start_mission(t, fc.mission_index) != 0:
                return mav.MAV_RESULT_FAILED
            state["mode"] = AUTO
            return mav.MAV_RESULT_ACCEPTED
        if mode == LAND:
            if fc.armed:
                fc.land(t)
            state["mode"] = LAND
            return mav.MAV_RESULT_ACCEPTED
        if mode == RTL:
            if not fc.armed:
                return mav.MAV_RESULT_FAILED  # ArduCopter cannot enter RTL on the ground
            fc.return_to_launch(t)
            state["mode"] = RTL
            return mav.MAV_RESULT_ACCEPTED
        return mav.MAV_RESULT_FAILED

    def _text(self, severity: int, text: str) -> None:
        """A STATUSTEXT from this instance (its client's request went wrong)."""
        self.send(self.tx.statustext_encode(severity, text.encode()[:50]))

    # ------------------------------------------------------------------ telemetry

    def _heartbeat(self, t: float):
        """HEARTBEAT: ArduPilot quadrotor, ArduCopter custom mode, STANDBY landed / ACTIVE flying."""
        fc, mode = self.v.fc, self.mode
        base = (mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | mav.MAV_MODE_FLAG_STABILIZE_ENABLED
                | mav.MAV_MODE_FLAG_MANUAL_INPUT_ENABLED)
        if mode in GUIDED_ENABLED_MODES:
            base |= mav.MAV_MODE_FLAG_GUIDED_ENABLED
        if fc.armed:
            base |= mav.MAV_MODE_FLAG_SAFETY_ARMED
        status = mav.MAV_STATE_STANDBY if fc.landed or not fc.armed else mav.MAV_STATE_ACTIVE
        return self.tx.heartbeat_encode(
            mav.MAV_TYPE_QUADROTOR, mav.MAV_AUTOPILOT_ARDUPILOTMEGA, base, mode, status, 3
        )

    def _vfr_hud(self, t: float):
        """VFR_HUD: ground speed, heading, throttle, altitude (AMSL) and climb rate."""
        _, r, v, _, p_enu = self._report(t)
        alt = self._lla_of_local(p_enu)[2]
        heading = int(round(math.degrees(euler_zyx(r)[2]))) % 360
        thrust = float(np.linalg.norm(self.v.fc.last_force))
        throttle = int(min(100, round(100 * thrust / (2 * self.v.fc.airframe.mass * 9.81))))
        speed = float(math.hypot(v[0], v[1]))
        return self.tx.vfr_hud_encode(speed, speed, heading, throttle, float(alt), float(-v[2]))

    def _autopilot_version(self, t: float):
        """AUTOPILOT_VERSION: ArduCopter's capabilities (C-cast parameters, no bytewise encoding)."""
        return self.tx.autopilot_version_encode(
            CAPABILITIES, COPTER_VERSION, 0, 0, 0, [0] * 8, [0] * 8, [0] * 8, 0x1209, 0x5740,
            0xA9D00000 + self.v.system_id,
        )

    def _mission_current(self, t: float):
        """MISSION_CURRENT: sequence numbers count home as item 0."""
        msg = super()._mission_current(t)
        if self.v.fc.mission:
            msg.seq = self.v.fc.mission[min(self.v.fc.mission_index, len(self.v.fc.mission) - 1)].seq
            msg.total = len(self.mission.plans[0])
        return msg

    def home_item(self) -> MissionItem:
        """Home as ArduPilot reports it: item 0, a waypoint at home's latitude, longitude and AMSL."""
        lat, lon, alt = self._lla_of_local(self.v.fc.home)
        return MissionItem(0, mav.MAV_FRAME_GLOBAL_INT, mav.MAV_CMD_NAV_WAYPOINT, 0, 1, 0.0, 0.0, 0.0, 0.0,
                           int(round(lat * 1e7)), int(round(lon * 1e7)), float(alt))

    def load_mission(self, items) -> None:
        """Item 0 of an upload is home's slot: the vehicle flies items 1..n."""
        super().load_mission(items[1:])

    def set_current(self, seq: int) -> None:
        """MISSION_SET_CURRENT counts home as item 0."""
        super().set_current(max(0, seq - 1))

    # ------------------------------------------------------------------ parameters

    def _on_param_request_list(self, m) -> None:
        """Send every parameter."""
        names = self.params.names
        for i, name in enumerate(names):
            self._send_param(name, i, len(names))

    def _on_param_request_read(self, m) -> None:
        """One parameter by index or name; unknown ones are counted and ignored."""
        names = self.params.names
        if m.param_index >= 0:
            if m.param_index < len(names):
                self._send_param(names[m.param_index], m.param_index, len(names))
            return
        name = _param_name(m.param_id)
        if name in names:
            self._send_param(name, names.index(name), len(names))
        else:
            self.stats["param_unknown"] += 1

    def _on_param_set(self, m) -> None:
        """Set a parameter and send its value on every instance; an SRn_ stream rate takes effect on
        instance n at once."""
        name, names = _param_name(m.param_id), self.params.names
        if name not in names:
            self.stats["param_unknown"] += 1
            return
        if self.params.set(name, float(m.param_value)):
            self._apply_stream_param(name)
        else:
            self.stats["param_rejected"] += 1
        for link in self.v.links:  # ArduPilot sends the new value on every channel
            link._send_param(name, names.index(name), len(names))

    def _apply_stream_param(self, name: str) -> None:
        """SRn_GROUP = hz: instance n's group follows."""
        if not name.startswith("SR") or "_" not in name:
            return
        prefix, group = name.split("_", 1)
        for link in self.v.links:
            if f"SR{link.instance}" == prefix:
                link.apply_stream_rate(group, min(self.params.get(name)[0], MAX_STREAM_HZ))

    def _send_param(self, name: str, index: int, count: int) -> None:
        """PARAM_VALUE with the value as a float (C cast) and the parameter's own type."""
        value, ptype = self.params.get(name)
        self.send(self.tx.param_value_encode(name.encode(), float(value), ptype, count, index))

    # ------------------------------------------------------------------ inbound

    def _on_request_data_stream(self, m) -> None:
        """REQUEST_DATA_STREAM: a group's rate (MAV_DATA_STREAM_ALL: every group), 0 / stop = off."""
        if m.start_stop not in (0, 1):
            return
        hz = float(min(m.req_message_rate, MAX_STREAM_HZ)) if m.start_stop == 1 else 0.0
        groups = [name for name, _ in STREAMS.values()] if m.req_stream_id == mav.MAV_DATA_STREAM_ALL else (
            [STREAMS[m.req_stream_id][0]] if m.req_stream_id in STREAMS else [])
        for group in groups:
            self.params.set(f"SR{self.instance}_{group}", hz)
            self.apply_stream_rate(group, hz)

    def _on_set_mode(self, m) -> None:
        """The legacy SET_MODE message, answered like ArduPilot with a COMMAND_ACK for message 11."""
        result = (self.set_mode(int(m.custom_mode)) if m.base_mode & mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
                  else mav.MAV_RESULT_FAILED)
        self.send(self.tx.command_ack_encode(mav.MAVLINK_MSG_ID_SET_MODE, result, 0, 0,
                                             m.get_srcSystem(), m.get_srcComponent()))

    def _on_set_position_target_local_ned(self, m) -> None:
        """Position targets steer the vehicle in GUIDED only (ignored otherwise, as ArduCopter does):
        a position is held until the next; velocities need a fresh target, as offboard ones do."""
        if self.mode != GUIDED:
            self.stats["setpoint_not_guided"] += 1
            return
        sp = self._position_target(m)
        if sp is None:
            return
        fc = self.v.fc
        if sp.vel is None and sp.yaw_rate is None and sp.pos is not None and np.isfinite(sp.pos).all():
            fc.reposition(self.sim.time, sp.pos, sp.yaw)
            return
        fc.set_offboard_setpoint(sp)
        if fc.main_mode != flight.MAIN_OFFBOARD:
            fc.set_mode(flight.MAIN_OFFBOARD, 0, self.sim.time)

    # ------------------------------------------------------------------ commands

    def _cmd_arm_copter(self, p, xy) -> int:
        """Arming needs an armable mode (not AUTO, LAND or RTL); disarming in the air needs force."""
        if math.isfinite(p[0]) and p[0] >= 0.5 and not self.v.fc.armed and self.mode not in ARMABLE_MODES:
            self._text(3, "Arm: Mode not armable")
            return mav.MAV_RESULT_FAILED
        result = self._cmd_arm(p, xy)
        return mav.MAV_RESULT_FAILED if result != mav.MAV_RESULT_ACCEPTED else result

    def _cmd_takeoff_copter(self, p, _xy) -> int:
        """MAV_CMD_NAV_TAKEOFF in GUIDED: param7 is the altitude above home in metres."""
        fc = self.v.fc
        if self.mode != GUIDED or not fc.armed or not fc.landed:
            return mav.MAV_RESULT_FAILED
        if not math.isfinite(p[6]):
            return mav.MAV_RESULT_FAILED
        return mav.MAV_RESULT_ACCEPTED if fc.takeoff(self.sim.time, p[6]) == 0 else mav.MAV_RESULT_FAILED

    def _cmd_land_copter(self, p, _xy) -> int:
        """MAV_CMD_NAV_LAND: switch to LAND."""
        return self.set_mode(LAND)

    def _cmd_rtl_copter(self, p, _xy) -> int:
        """MAV_CMD_NAV_RETURN_TO_LAUNCH: switch to RTL."""
        return self.set_mode(RTL)

    def _cmd_set_mode_copter(self, p, _xy) -> int:
        """MAV_CMD_DO_SET_MODE: param2 is the ArduCopter mode number."""
        if not all(math.isfinite(x) for x in p[:2]) or not int(p[0]) & mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
            return mav.MAV_RESULT_FAILED
        return self.set_mode(int(p[1]))

    def _cmd_mission_start_copter(self, p, _xy) -> int:
        """MAV_CMD_MISSION_START: AUTO from the current item (home, item 0, is not flown)."""
        fc = self.v.fc
        if not fc.armed or not fc.mission:
            return mav.MAV_RESULT_FAILED
        first = int(p[0]) - 1 if math.isfinite(p[0]) and p[0] >= 1 else fc.mission_index
        if fc.start_mission(self.sim.time, first) != 0:
            return mav.MAV_RESULT_FAILED
        self.v.autopilot_state["mode"] = AUTO
        return mav.MAV_RESULT_ACCEPTED

    def _cmd_reposition_copter(self, p, xy) -> int:
        """MAV_CMD_DO_REPOSITION: fly there in GUIDED."""
        result = self._cmd_reposition(p, xy)
        if result == mav.MAV_RESULT_ACCEPTED:
            self.v.autopilot_state["mode"] = GUIDED
        return mav.MAV_RESULT_FAILED if result != mav.MAV_RESULT_ACCEPTED else result

    def _cmd_set_message_interval_copter(self, p, xy) -> int:
        """MAV_CMD_SET_MESSAGE_INTERVAL: a message ArduPilot does not send (ODOMETRY) fails; 0 resets to
        the rate of its stream group."""
        msg_id = int(p[0]) if math.isfinite(p[0]) else -1
        if msg_id not in self.producers or msg_id == mav.MAVLINK_MSG_ID_AUTOPILOT_VERSION:
            self._text(6, f"No ap_message for mavlink id ({msg_id})")
            return mav.MAV_RESULT_FAILED
        result = self._cmd_set_message_interval(p, xy)
        return mav.MAV_RESULT_FAILED if result != mav.MAV_RESULT_ACCEPTED else result


ARDUCOPTER_COMMANDS = {
    mav.MAV_CMD_COMPONENT_ARM_DISARM: ArduCopterLink._cmd_arm_copter,
    mav.MAV_CMD_NAV_TAKEOFF: ArduCopterLink._cmd_takeoff_copter,
    mav.MAV_CMD_NAV_LAND: ArduCopterLink._cmd_land_copter,
    mav.MAV_CMD_NAV_RETURN_TO_LAUNCH: ArduCopterLink._cmd_rtl_copter,
    mav.MAV_CMD_DO_SET_MODE: ArduCopterLink._cmd_set_mode_copter,
    mav.MAV_CMD_MISSION_START: ArduCopterLink._cmd_mission_start_copter,
    mav.MAV_CMD_DO_REPOSITION: ArduCopterLink._cmd_reposition_copter,
    mav.MAV_CMD_SET_MESSAGE_INTERVAL: ArduCopterLink._cmd_set_message_interval_copter,
}
ArduCopterLink.commands = {**COMMANDS, **ARDUCOPTER_COMMANDS}

"""One MAVLink instance of a vehicle (PX4 SITL style): telemetry streams, commands, params, missions.

A vehicle has one instance per client class, as PX4 has: an onboard/API instance (sends to port
14540 + i, where coopd or MAVSDK listen) and optionally a GCS instance (sends to 14550, where
QGroundControl or MAVProxy listen), each with its own socket, parser and stream rates."""

from __future__ import annotations

import math
import socket
import struct
import time
from collections import Counter

import numpy as np
from pymavlink.dialects.v20 import common as mav

from firmware_sim import flight
from firmware_sim.collision import bins_from_message
from firmware_sim.flight import Setpoint
from firmware_sim.frames import ENU_TO_NED, enu_flu_to_ned_frd, euler_zyx, mat_to_quat, wrap_pi
from firmware_sim.mission_protocol import MissionServer, nav_target
from firmware_sim.odometry import WORLD_ORIGIN_LLA, lla_to_world, world_to_lla

MAX_DATAGRAMS_PER_POLL = 64
MAX_DATAGRAM = 2048
MAX_STATUSTEXT_PER_TICK = 4

# Default stream rates in Hz of simulated time of the onboard/API instance (PX4 "onboard"-like, trimmed).
DEFAULT_RATES_HZ = {
    mav.MAVLINK_MSG_ID_HEARTBEAT: 1.0,
    mav.MAVLINK_MSG_ID_SYS_STATUS: 1.0,
    mav.MAVLINK_MSG_ID_SYSTEM_TIME: 1.0,
    mav.MAVLINK_MSG_ID_ATTITUDE: 20.0,
    mav.MAVLINK_MSG_ID_ATTITUDE_QUATERNION: 20.0,
    mav.MAVLINK_MSG_ID_LOCAL_POSITION_NED: 20.0,
    mav.MAVLINK_MSG_ID_ODOMETRY: 30.0,
    mav.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: 10.0,
    mav.MAVLINK_MSG_ID_GPS_RAW_INT: 1.0,
    mav.MAVLINK_MSG_ID_HOME_POSITION: 0.5,
    mav.MAVLINK_MSG_ID_EXTENDED_SYS_STATE: 5.0,
    mav.MAVLINK_MSG_ID_BATTERY_STATUS: 0.5,
    mav.MAVLINK_MSG_ID_MISSION_CURRENT: 1.0,
}
# The GCS instance (PX4 "normal" mode, trimmed): what a ground station displays, no ODOMETRY.
GCS_RATES_HZ = {
    mav.MAVLINK_MSG_ID_HEARTBEAT: 1.0,
    mav.MAVLINK_MSG_ID_SYS_STATUS: 1.0,
    mav.MAVLINK_MSG_ID_SYSTEM_TIME: 1.0,
    mav.MAVLINK_MSG_ID_ATTITUDE: 10.0,
    mav.MAVLINK_MSG_ID_LOCAL_POSITION_NED: 2.0,
    mav.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: 5.0,
    mav.MAVLINK_MSG_ID_GPS_RAW_INT: 1.0,
    mav.MAVLINK_MSG_ID_HOME_POSITION: 0.5,
    mav.MAVLINK_MSG_ID_EXTENDED_SYS_STATE: 1.0,
    mav.MAVLINK_MSG_ID_BATTERY_STATUS: 0.5,
    mav.MAVLINK_MSG_ID_MISSION_CURRENT: 1.0,
}
SENSORS = (
    mav.MAV_SYS_STATUS_SENSOR_3D_GYRO
    | mav.MAV_SYS_STATUS_SENSOR_3D_ACCEL
    | mav.MAV_SYS_STATUS_SENSOR_3D_MAG
    | mav.MAV_SYS_STATUS_SENSOR_ABSOLUTE_PRESSURE
    | mav.MAV_SYS_STATUS_SENSOR_GPS
    | mav.MAV_SYS_STATUS_SENSOR_ANGULAR_RATE_CONTROL
    | mav.MAV_SYS_STATUS_SENSOR_ATTITUDE_STABILIZATION
    | mav.MAV_SYS_STATUS_SENSOR_XY_POSITION_CONTROL
    | mav.MAV_SYS_STATUS_SENSOR_Z_ALTITUDE_CONTROL
    | mav.MAV_SYS_STATUS_SENSOR_MOTOR_OUTPUTS
    | mav.MAV_SYS_STATUS_PREARM_CHECK
)
CAPABILITIES = (
    mav.MAV_PROTOCOL_CAPABILITY_MISSION_FLOAT
    | mav.MAV_PROTOCOL_CAPABILITY_PARAM_FLOAT
    | mav.MAV_PROTOCOL_CAPABILITY_MISSION_INT
    | mav.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
    | mav.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE
    | mav.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_LOCAL_NED
    | mav.MAV_PROTOCOL_CAPABILITY_MAVLINK2
)
INT_PARAMS = {"MAV_SYS_ID", "SYS_AUTOSTART", "MAV_TYPE", "CP_GO_NO_DATA"}
FORCE_DISARM_MAGIC = 21196

# SET_POSITION_TARGET type_mask bits
IGNORE_POS = (1, 2, 4)
IGNORE_VEL = (8, 16, 32)
IGNORE_YAW, IGNORE_YAW_RATE = 1024, 2048


class _Writer:
    """File-like sink pymavlink writes packed messages into; sends each as one UDP datagram."""

    def __init__(self, link: MavlinkLink):
        self.link = link

    def write(self, buf: bytes) -> None:
        """Send without blocking; a full socket buffer is a counted drop, never an exception."""
        try:
            self.link.sock.sendto(buf, self.link.target)
            self.link.stats["tx"] += 1
        except (BlockingIOError, InterruptedError):
            self.link.stats["tx_dropped"] += 1
        except OSError:
            self.link.stats["tx_errors"] += 1


def ned_to_enu(v) -> np.ndarray:
    """NED vector to the ENU-like reporting frame by swapping, so unset (NaN) components stay apart."""
    return np.array([v[1], v[0], -v[2]], dtype=float)


def take_vehicle_events(fc) -> tuple[list[int], list[tuple[int, str]]]:
    """The flight controller's new events (mission items reached, STATUSTEXTs, bounded per tick),
    taken once per step so that every MAVLink instance of the vehicle sends the same ones."""
    reached, fc.reached_events = fc.reached_events, []
    texts = fc.messages[:MAX_STATUSTEXT_PER_TICK]
    del fc.messages[:MAX_STATUSTEXT_PER_TICK]
    return reached, texts


class MavlinkLink:
    """Bound to <bind_host>:<bind_port or ephemeral>, sends to the client's UDP port, answers whoever
    talks to it. `rates` (Hz by message id) are this instance's default streams; `instance` numbers
    the vehicle's instances (0 = onboard/API, 1 = GCS)."""

    default_rates: dict[int, float] = DEFAULT_RATES_HZ
    commands: dict  # MAV_CMD -> handler(self, params, int_xy) returning a MAV_RESULT; set below

    def __init__(self, sim, vehicle, target: tuple[str, int], bind_port: int = 0,
                 bind_host: str = "127.0.0.1", rates: dict[int, float] | None = None, instance: int = 0):
        self.sim, self.v, self.target, self.bind_host = sim, vehicle, target, bind_host
        self.instance = instance
        if rates is not None:
            self.default_rates = dict(rates)
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind((bind_host, bind_port))
        self.sock.setblocking(False)
        self.bound_port = self.sock.getsockname()[1]
        self.stats: Counter = Counter()
        self.tx = mav.MAVLink(_Writer(self), srcSystem=vehicle.system_id, srcComponent=1)
        self.rx = mav.MAVLink(None, srcSystem=vehicle.system_id, srcComponent=1)
        self.rx.robust_parsing = True
        self.intervals = {m: 1.0 / hz if hz > 0 else 0.0 for m, hz in self.default_rates.items()}
        self.next_due = dict.fromkeys(self.intervals, 0.0)
        self.mission = MissionServer(self)
        self._earliest_due = 0.0
        self._after_ack: list[int] = []
        self.boot_wall = time.time()
        self._report_cache: tuple[float, tuple] | None = None
        self._last_mission_seq = -1
        self.producers = {
            mav.MAVLINK_MSG_ID_HEARTBEAT: self._heartbeat,
            mav.MAVLINK_MSG_ID_SYS_STATUS: self._sys_status,
            mav.MAVLINK_MSG_ID_SYSTEM_TIME: self._system_time,
            mav.MAVLINK_MSG_ID_ATTITUDE: self._attitude,
            mav.MAVLINK_MSG_ID_ATTITUDE_QUATERNION: self._attitude_quaternion,
            mav.MAVLINK_MSG_ID_LOCAL_POSITION_NED: self._local_position,
            mav.MAVLINK_MSG_ID_ODOMETRY: self._odometry,
            mav.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: self._global_position,
            mav.MAVLINK_MSG_ID_GPS_RAW_INT: self._gps_raw,
            mav.MAVLINK_MSG_ID_HOME_POSITION: self._home_position,
            mav.MAVLINK_MSG_ID_EXTENDED_SYS_STATE: self._extended_sys_state,
            mav.MAVLINK_MSG_ID_BATTERY_STATUS: self._battery,
            mav.MAVLINK_MSG_ID_MISSION_CURRENT: self._mission_current,
            mav.MAVLINK_MSG_ID_AUTOPILOT_VERSION: self._autopilot_version,
        }
        self._interval_reply = (0, -1)
        self._covariances = self._covariance_lists()

    # ------------------------------------------------------------------ plumbing

    def fileno(self) -> int:
        """The UDP socket, for select()."""
        return self.sock.fileno()

    def send(self, msg) -> None:
        """Pack and send one message."""
        try:
            self.tx.send(msg)
        except Exception:  # a message we built that pymavlink cannot pack is our bug: count, don't die
            self.stats["tx_pack_errors"] += 1

    def close(self) -> None:
        """Close the socket."""
        self.sock.close()

    def poll(self, t: float) -> None:
        """Read and handle pending datagrams (bounded), then run protocol timers; while the flight
        controller reboots, whatever arrives is read and lost."""
        down = self.v.fc_rebooting(t)
        for _ in range(MAX_DATAGRAMS_PER_POLL):
            try:
                data, _addr = self.sock.recvfrom(MAX_DATAGRAM)
            except (BlockingIOError, InterruptedError):
                break
            except OSError:
                self.stats["rx_errors"] += 1
                break
            if down:
                self.stats["rx_while_rebooting"] += 1
                continue
            self.stats["rx_datagrams"] += 1
            self._reset_parser()
            try:
                msgs = self.rx.parse_buffer(data) or []
            except Exception:  # hostile bytes: pymavlink may raise on anything malformed
                self.stats["rx_parse_errors"] += 1
                continue
            for m in msgs:
                try:
                    self._dispatch(m)
                except Exception:  # a field combination we did not foresee must not stop the vehicle
                    self.stats["rx_handler_errors"] += 1
        self.mission.tick()

    def _reset_parser(self) -> None:
        """Each UDP datagram holds whole packets: never let a broken one swallow the next datagram."""
        if self.rx.buf_index < len(self.rx.buf):
            self.stats["rx_partial_discarded"] += 1
        self.rx.buf = bytearray()
        self.rx.buf_index = 0
        self.rx.expected_length = mav.HEADER_LEN_V1 + 2
        self.rx.have_prefix_error = False

    def on_sim_step(self, t: float, reached=(), texts=()) -> None:
        """Send the step's vehicle events (take_vehicle_events) and due telemetry; called after every
        physics step."""
        if self.v.fc_rebooting(t):
            return  # the endpoint is silent while the flight controller reboots
        fc = self.v.fc
        for seq in reached:
            self.send(self.tx.mission_item_reached_encode(seq))
        for sev, text in texts:
            self.send(self.tx.statustext_encode(sev, text.encode()[:50]))
        if fc.mission_index != self._last_mission_seq:
            self._last_mission_seq = fc.mission_index
            self._emit(mav.MAVLINK_MSG_ID_MISSION_CURRENT, t)
        if t + 1e-9 < self._earliest_due:
            return
        for msg_id, interval in self.intervals.items():
            if interval > 0 and t + 1e-9 >= self.next_due[msg_id]:
                self.next_due[msg_id] = max(self.next_due[msg_id] + interval, t - interval)
                self._emit(msg_id, t)
        self._earliest_due = min(
            (self.next_due[k] for k, iv in self.intervals.items() if iv > 0), default=math.inf
        )

    def _emit(self, msg_id: int, t: float) -> None:
        """Produce and send one message by id (-1: the pending MESSAGE_INTERVAL reply)."""
        if msg_id == -1:
            self.send(self.tx.message_interval_encode(*self._interval_reply))
            return
        self.send(self.producers[msg_id](t - self.v.boot_offset))  # producers stamp time since boot

    def restart(self) -> None:
        """The flight controller booted again: a new MAVLink sequence, default stream rates (a
        SET_MESSAGE_INTERVAL does not survive a reboot), timers from now; the socket stays bound."""
        self.tx = mav.MAVLink(_Writer(self), srcSystem=self.v.system_id, srcComponent=1)
        self.intervals = {m: 1.0 / hz if hz > 0 else 0.0 for m, hz in self.default_rates.items()}
        self.next_due = dict.fromkeys(self.intervals, self.sim.time)
        self._earliest_due = self.sim.time
        self._after_ack = []
        self._report_cache = None
        self.stats["restarts"] += 1

    # ------------------------------------------------------------------ state views

    def _report(self, t: float):
        """Noisy reported state at time t (cached per step): pos/vel NED, rot NED-FRD, rates FRD."""
        if self._report_cache is not None and self._report_cache[0] == t:
            return self._report_cache[1]
        s = self.sim.estimated_state(self.v)
        p, r, vel = self.v.odometry.noisy(s.pos, s.rot, s.vel)
        rates = np.array([s.omega_body[0], -s.omega_body[1], -s.omega_body[2]])
        out = (ENU_TO_NED @ p, enu_flu_to_ned_frd(r), ENU_TO_NED @ vel, rates, p)
        self._report_cache = (t, out)
        return out

    def _lla_of_local(self, p_local_enu) -> tuple[float, float, float]:
        """Geodetic position of a point of the reporting frame."""
        return world_to_lla(self.v.odometry.local_to_world_point(p_local_enu))

    def lla_to_local(self, lat: float, lon: float, alt_amsl: float) -> np.ndarray:
        """A geodetic position in the reporting frame (ENU-like)."""
        return self.v.odometry.world_to_local_point(lla_to_world(lat, lon, alt_amsl))

    def _home_amsl(self) -> float:
        """Home altitude above mean sea level."""
        return self._lla_of_local(self.v.fc.home)[2]

    # ------------------------------------------------------------------ telemetry producers

    def _heartbeat(self, t: float):
        """HEARTBEAT: PX4 quadrotor, armed flag, PX4 custom mode (main << 16 | sub << 24)."""
        fc = self.v.fc
        base = mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | mav.MAV_MODE_FLAG_STABILIZE_ENABLED
        if fc.main_mode in (flight.MAIN_AUTO, flight.MAIN_OFFBOARD):
            base |= mav.MAV_MODE_FLAG_GUIDED_ENABLED | mav.MAV_MODE_FLAG_AUTO_ENABLED
        if fc.armed:
            base |= mav.MAV_MODE_FLAG_SAFETY_ARMED
        custom = (fc.main_mode << 16) | (fc.sub_mode << 24)
        status = mav.MAV_STATE_ACTIVE if fc.armed else mav.MAV_STATE_STANDBY
        return self.tx.heartbeat_encode(
            mav.MAV_TYPE_QUADROTOR, mav.MAV_AUTOPILOT_PX4, base, custom, status, 3
        )

    def _sys_status(self, t: float):
        """SYS_STATUS: every sensor present, enabled and healthy, pre-arm checks passing."""
        return self.tx.sys_status_encode(SENSORS, SENSORS, SENSORS, 200, 16000, 500, 90, 0, 0, 0, 0, 0, 0)

    def _system_time(self, t: float):
        """SYSTEM_TIME: wall-clock Unix time plus the simulated time since boot."""
        unix = self.boot_wall + self.v.boot_offset + t
        return self.tx.system_time_encode(int(unix * 1e6), int(t * 1000) & 0xFFFFFFFF)

    def _attitude(self, t: float):
        """ATTITUDE: reported roll, pitch, yaw (NED/FRD) and body rates."""
        _, r, _, w, _ = self._report(t)
        roll, pitch, yaw = euler_zyx(r)
        return self.tx.attitude_encode(int(t * 1000) & 0xFFFFFFFF, roll, pitch, yaw, *map(float, w))

    def _attitude_quaternion(self, t: float):
        """ATTITUDE_QUATERNION: reported attitude (w, x, y, z) and body rates."""
        _, r, _, w, _ = self._report(t)
        q = mat_to_quat(r)
        return self.tx.attitude_quaternion_encode(
            int(t * 1000) & 0xFFFFFFFF, *map(float, q), *map(float, w), [0.0, 0.0, 0.0, 0.0]
        )

    def _local_position(self, t: float):
        """LOCAL_POSITION_NED: reported position and velocity in the vehicle's local frame."""
        p, _, v, _, _ = self._report(t)
        return self.tx.local_position_ned_encode(int(t * 1000) & 0xFFFFFFFF, *map(float, p), *map(float, v))

    def _odometry(self, t: float):
        """ODOMETRY: local NED pose, body-FRD velocity and rates, covariances from the noise model."""
        p, r, v, w, _ = self._report(t)
        v_body = r.T @ v
        pc, vc = self._covariances
        return self.tx.odometry_encode(
            int(t * 1e6),
            mav.MAV_FRAME_LOCAL_NED,
            mav.MAV_FRAME_BODY_FRD,
            *map(float, p),
            [float(x) for x in mat_to_quat(r)],
            *map(float, v_body),
            *map(float, w),
            pc,
            vc,
            self.v.odometry.reset_counter & 0xFF,
            mav.MAV_ESTIMATOR_TYPE_VIO,
            100,
        )

    def _covariance_lists(self) -> tuple[list[float], list[float]]:
        """ODOMETRY's pose and velocity covariances (upper triangles) from the noise model."""
        n = self.v.odometry.noise
        pc, vc = [math.nan] * 21, [math.nan] * 21
        for k in (0, 6, 11):
            pc[k] = max(n.pos_sigma_m, 1e-3) ** 2
            vc[k] = max(n.vel_sigma_m_s, 1e-3) ** 2
        for k in (15, 18, 20):
            pc[k] = max(n.att_sigma_rad, 1e-3) ** 2
        return pc, vc

    def _global_position(self, t: float):
        """GLOBAL_POSITION_INT: the estimate mapped to latitude/longitude (flat earth)."""
        p, r, v, _, p_enu = self._report(t)
        lat, lon, alt = self._lla_of_local(p_enu)
        rel = p_enu[2] - self.v.fc.home[2]
        hdg = int(round(math.degrees(euler_zyx(r)[2]) * 100)) % 36000
        return self.tx.global_position_int_encode(
            int(t * 1000) & 0xFFFFFFFF,
            int(round(lat * 1e7)),
            int(round(lon * 1e7)),
            int(round(alt * 1000)),
            int(round(rel * 1000)),
            *(int(np.clip(round(x * 100), -32768, 32767)) for x in v),
            hdg,
        )

    def _gps_raw(self, t: float):
        """GPS_RAW_INT: a steady 3D fix at the estimated position (MAVSDK's gps info)."""
        _, _, _, _, p_enu = self._report(t)
        lat, lon, alt = self._lla_of_local(p_enu)
        return self.tx.gps_raw_int_encode(
            int(t * 1e6),
            3,
            int(round(lat * 1e7)),
            int(round(lon * 1e7)),
            int(round(alt * 1000)),
            80,
            120,
            0,
            65535,
            12,
        )

    def _home_position(self, t: float):
        """HOME_POSITION: where the vehicle armed, geodetic and local."""
        h = self.v.fc.home
        lat, lon, alt = self._lla_of_local(h)
        hn = ENU_TO_NED @ h
        return self.tx.home_position_encode(
            int(round(lat * 1e7)),
            int(round(lon * 1e7)),
            int(round(alt * 1000)),
            *map(float, hn),
            [1.0, 0.0, 0.0, 0.0],
            0.0,
            0.0,
            0.0,
            int(t * 1e6),
        )

    def _extended_sys_state(self, t: float):
        """EXTENDED_SYS_STATE: multicopter, landed state from the flight controller."""
        return self.tx.extended_sys_state_encode(0, self.v.fc.flight_status())

    def _battery(self, t: float):
        """BATTERY_STATUS: a healthy 4S battery (the emulator does not drain it)."""
        cells = [4000, 4000, 4000, 4000] + [65535] * 6
        return self.tx.battery_status_encode(0, 0, 0, 2500, cells, 500, -1, -1, 90)

    def _mission_current(self, t: float):
        """MISSION_CURRENT: current item, total, and mission state."""
        fc = self.v.fc
        total = len(self.mission.plans[0])
        seq = min(fc.mission_index, max(0, total - 1)) if total else 0
        if not total:
            state = 1
        elif fc.mission_index >= len(fc.mission):
            state = 5
        elif fc.main_mode == flight.MAIN_AUTO and fc.sub_mode == flight.SUB_MISSION:
            state = 3
        else:
            state = 4 if fc.armed else 2
        return self.tx.mission_current_encode(
            seq, total, state, 1 if fc.sub_mode == flight.SUB_MISSION else 0
        )

    def _autopilot_version(self, t: float):
        """AUTOPILOT_VERSION: capabilities (mission/command int, bytewise params, MAVLink 2)."""
        uid = 0x5EED0000 + self.v.system_id
        return self.tx.autopilot_version_encode(
            CAPABILITIES,
            (1 << 24) | (15 << 16) | (0 << 8) | 255,
            0,
            0,
            0,
            [0] * 8,
            [0] * 8,
            [0] * 8,
            0x26AC,
            0x1,
            uid,
        )

    # ------------------------------------------------------------------ inbound

    def _dispatch(self, m) -> None:
        """Route one decoded message; anything addressed to another system is ignored."""
        t = m.get_type()
        if t == "BAD_DATA":
            self.stats["rx_bad_data"] += 1
            return
        self.stats["rx_messages"] += 1
        target = getattr(m, "target_system", 0)
        if target not in (0, self.v.system_id):
            self.stats["rx_foreign"] += 1
            return
        if self.mission.handle(m):
            return
        handler = getattr(self, "_on_" + t.lower(), None)
        if handler is None:
            self.stats["rx_ignored"] += 1
            return
        handler(m)

    def _on_heartbeat(self, m) -> None:
        """Count the peer's heartbeats (visible in stats)."""
        self.stats["peer_heartbeats"] += 1

    def _on_timesync(self, m) -> None:
        """Answer a TIMESYNC request with our clock in nanoseconds."""
        if m.tc1 == 0:
            self.send(self.tx.timesync_encode(int((self.sim.time - self.v.boot_offset) * 1e9), m.ts1))

    def _on_param_request_list(self, m) -> None:
        """Send every parameter."""
        params = self.v.fc.params
        for i, name in enumerate(sorted(params)):
            self._send_param(name, i, len(params))

    def _on_param_request_read(self, m) -> None:
        """Send one parameter by name or index; unknown ones are counted and ignored."""
        params = self.v.fc.params
        names = sorted(params)
        name = _param_name(m.param_id)
        if m.param_index >= 0:
            if m.param_index < len(names):
                self._send_param(names[m.param_index], m.param_index, len(names))
            return
        if name in params:
            self._send_param(name, names.index(name), len(names))
        else:
            self.stats["param_unknown"] += 1

    def _on_param_set(self, m) -> None:
        """Set a known parameter (NaN refused) and send its value on every instance; unknown ones are
        ignored."""
        params = self.v.fc.params
        name = _param_name(m.param_id)
        if name not in params:
            self.stats["param_unknown"] += 1
            return
        if name in INT_PARAMS:
            value = struct.unpack("<i", struct.pack("<f", m.param_value))[0]
        else:
            value = float(m.param_value)
            if not math.isfinite(value):
                self.stats["param_rejected"] += 1
                value = params[name]
        if name != "MAV_SYS_ID":
            params[name] = value
        names = sorted(params)
        for link in self.v.links:  # PX4 sends a changed parameter on every MAVLink instance
            link._send_param(name, names.index(name), len(names))

    def _send_param(self, name: str, index: int, count: int) -> None:
        """Send PARAM_VALUE; integers use PX4's bytewise encoding."""
        value = self.v.fc.params[name]
        if name in INT_PARAMS:
            f = struct.unpack("<f", struct.pack("<i", int(value)))[0]
            ptype = mav.MAV_PARAM_TYPE_INT32
        else:
            f, ptype = float(value), mav.MAV_PARAM_TYPE_REAL32
        self.send(self.tx.param_value_encode(name.encode(), f, ptype, count, index))

    def _on_obstacle_distance(self, m) -> None:
        """OBSTACLE_DISTANCE: the flight controller's obstacle bins (collision prevention, CP_DIST)."""
        s = self.sim.estimated_state(self.v)
        bins = bins_from_message(m, euler_zyx(enu_flu_to_ned_frd(s.rot))[2], self.sim.time)
        if bins is None:
            self.stats["obstacle_distance_refused"] += 1
            return
        self.v.fc.obstacles = bins
        self.stats["obstacle_distance"] += 1

    def _on_set_position_target_local_ned(self, m) -> None:
        """Offboard setpoint in local NED (or body / offset frames), honouring type_mask."""
        sp = self._position_target(m)
        if sp is not None:
            self.v.fc.set_offboard_setpoint(sp)

    def _position_target(self, m) -> Setpoint | None:
        """SET_POSITION_TARGET_LOCAL_NED as a local-ENU Setpoint; None (counted) if unusable."""
        mask = m.type_mask
        pos = np.array(
            [math.nan if mask & b else v for b, v in zip(IGNORE_POS, (m.x, m.y, m.z), strict=True)]
        )
        vel = np.array(
            [math.nan if mask & b else v for b, v in zip(IGNORE_VEL, (m.vx, m.vy, m.vz), strict=True)]
        )
        yaw = None if mask & IGNORE_YAW or not math.isfinite(m.yaw) else float(m.yaw)
        yaw_rate = None if mask & IGNORE_YAW_RATE or not math.isfinite(m.yaw_rate) else float(m.yaw_rate)
        if (
            np.isinf(pos).any()
            or np.isinf(vel).any()
            or (yaw is not None and abs(yaw) > 100)
            or (yaw_rate is not None and abs(yaw_rate) > 100)
        ):
            self.stats["setpoint_invalid"] += 1
            return None
        s = self.sim.estimated_state(self.v)
        here = ENU_TO_NED @ s.pos
        yaw_now = euler_zyx(enu_flu_to_ned_frd(s.rot))[2]
        frame = m.coordinate_frame
        if frame in (mav.MAV_FRAME_BODY_NED, mav.MAV_FRAME_BODY_OFFSET_NED):
            c, sn = math.cos(yaw_now), math.sin(yaw_now)
            rz = np.array([[c, -sn, 0.0], [sn, c, 0.0], [0.0, 0.0, 1.0]])
            pos, vel = _rotate_keeping_unset(rz, pos), _rotate_keeping_unset(rz, vel)
            pos = here + np.nan_to_num(pos) if np.isfinite(pos).any() else pos
        elif frame == mav.MAV_FRAME_LOCAL_OFFSET_NED:
            pos = here + np.nan_to_num(pos) if np.isfinite(pos).any() else pos
        elif frame != mav.MAV_FRAME_LOCAL_NED:
            self.stats["setpoint_bad_frame"] += 1
            return None
        has_pos, has_vel = bool(np.isfinite(pos).any()), bool(np.isfinite(vel).any())
        if not (has_pos or has_vel) and yaw is None and yaw_rate is None:
            self.stats["setpoint_empty"] += 1
            return None
        sp = Setpoint(
            pos=ned_to_enu(pos) if has_pos else None,
            vel=ned_to_enu(vel) if has_vel else None,
            yaw=None if yaw is None else wrap_pi(math.pi / 2 - yaw),
            yaw_rate=None if yaw_rate is None else -yaw_rate,
        )
        if sp.pos is None and sp.vel is None:
            sp.pos = s.pos.copy()
        return sp

    # ------------------------------------------------------------------ commands

    def _on_command_long(self, m) -> None:
        """COMMAND_LONG: params 1-7 as floats."""
        p = [m.param1, m.param2, m.param3, m.param4, m.param5, m.param6, m.param7]
        self._command(m, m.command, p, is_int=False)

    def _on_command_int(self, m) -> None:
        """COMMAND_INT: x, y as 1e-7 degrees, z as float."""
        p = [m.param1, m.param2, m.param3, m.param4, m.x * 1e-7, m.y * 1e-7, m.z]
        self._command(m, m.command, p, is_int=True, int_xy=(m.x, m.y))

    def _command(self, m, command: int, p: list, is_int: bool, int_xy=None) -> None:
        """Execute a command and always answer with COMMAND_ACK carrying the right MAV_RESULT."""
        handler = self.commands.get(command)
        if handler is None:
            result = mav.MAV_RESULT_UNSUPPORTED
        else:
            try:
                result = handler(self, p, int_xy)
            except (ValueError, OverflowError, TypeError):
                result = mav.MAV_RESULT_DENIED
        self.stats[f"cmd_{command}_{result}"] += 1
        self.send(self.tx.command_ack_encode(command, result, 0, 0, m.get_srcSystem(), m.get_srcComponent()))
        after, self._after_ack = self._after_ack, []
        for msg_id in after:  # requested messages follow their ACK
            self._emit(msg_id, self.sim.time)

    def load_mission(self, items) -> None:
        """Hand an uploaded flight plan to the flight controller."""
        home_z = self.v.fc.home[2]
        self.v.fc.load_mission([nav_target(it, self.lla_to_local, home_z) for it in items])

    def set_current(self, seq: int) -> None:
        """MISSION_SET_CURRENT: continue the plan from item seq."""
        self.v.fc.mission_index = seq
        self.v.fc.mission_hold_until = None

    def _cmd_arm(self, p, _xy) -> int:
        """MAV_CMD_COMPONENT_ARM_DISARM (param2 21196 forces a disarm in the air)."""
        fc = self.v.fc
        if not math.isfinite(p[0]):
            return mav.MAV_RESULT_DENIED
        if p[0] >= 0.5:
            return fc.arm(self.sim.time)
        return fc.disarm(self.sim.time, force=int(p[1]) == FORCE_DISARM_MAGIC)

    def _cmd_takeoff(self, p, _xy) -> int:
        """MAV_CMD_NAV_TAKEOFF: param7 is AMSL altitude, NaN means MIS_TAKEOFF_ALT above home."""
        alt = p[6]
        rel = None if not math.isfinite(alt) else alt - self._home_amsl()
        return self.v.fc.takeoff(self.sim.time, rel)

    def _cmd_land(self, p, _xy) -> int:
        """MAV_CMD_NAV_LAND where the vehicle is."""
        return self.v.fc.land(self.sim.time)

    def _cmd_rtl(self, p, _xy) -> int:
        """MAV_CMD_NAV_RETURN_TO_LAUNCH."""
        return self.v.fc.return_to_launch(self.sim.time)

    def _cmd_set_mode(self, p, _xy) -> int:
        """MAV_CMD_DO_SET_MODE with PX4 custom main/sub modes."""
        if not all(math.isfinite(x) for x in p[:3]) or not int(p[0]) & mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
            return mav.MAV_RESULT_DENIED
        return self.v.fc.set_mode(int(p[1]), int(p[2]), self.sim.time)

    def _cmd_mission_start(self, p, _xy) -> int:
        """MAV_CMD_MISSION_START from param1 (first item)."""
        first = int(p[0]) if math.isfinite(p[0]) and p[0] >= 0 else 0
        return self.v.fc.start_mission(self.sim.time, first)

    def _cmd_reposition(self, p, xy) -> int:
        """MAV_CMD_DO_REPOSITION: go to lat/lon/alt (NaN keeps current) and hold."""
        s = self.sim.estimated_state(self.v)
        lat, lon = (xy[0] * 1e-7, xy[1] * 1e-7) if xy is not None else (p[4], p[5])
        has_xy = math.isfinite(lat) and math.isfinite(lon) and not (xy is not None and xy == (0, 0))
        target = self.lla_to_local(lat, lon, 0.0) if has_xy else s.pos.copy()
        target[2] = (
            p[6] - WORLD_ORIGIN_LLA[2] - self.v.odometry.origin[2] if math.isfinite(p[6]) else s.pos[2]
        )
        yaw = wrap_pi(math.pi / 2 - p[3]) if math.isfinite(p[3]) else None
        return self.v.fc.reposition(self.sim.time, target, yaw)

    def _cmd_change_speed(self, p, _xy) -> int:
        """MAV_CMD_DO_CHANGE_SPEED: horizontal cruise speed (param2, m/s)."""
        if not (math.isfinite(p[1]) and 0 < p[1] <= 20):
            return mav.MAV_RESULT_DENIED
        self.v.fc.cruise_speed = float(p[1])
        return mav.MAV_RESULT_ACCEPTED

    def _cmd_set_message_interval(self, p, _xy) -> int:
        """MAV_CMD_SET_MESSAGE_INTERVAL: microseconds, 0 default, -1 off."""
        msg_id, interval_us = int(p[0]), p[1]
        if msg_id not in self.producers or msg_id == mav.MAVLINK_MSG_ID_AUTOPILOT_VERSION:
            return mav.MAV_RESULT_UNSUPPORTED
        if not math.isfinite(interval_us):
            return mav.MAV_RESULT_DENIED
        if interval_us == 0:
            rate = self.default_rates.get(msg_id, 0.0)
            self.intervals[msg_id] = 1.0 / rate if rate else 0.0
        elif interval_us < 0:
            self.intervals[msg_id] = 0.0
        else:
            self.intervals[msg_id] = max(interval_us * 1e-6, 0.004)
        self.next_due[msg_id] = self.sim.time
        self._earliest_due = self.sim.time
        return mav.MAV_RESULT_ACCEPTED

    def _cmd_get_message_interval(self, p, _xy) -> int:
        """MAV_CMD_GET_MESSAGE_INTERVAL: answer with MESSAGE_INTERVAL after the ACK."""
        msg_id = int(p[0])
        if msg_id not in self.producers:
            return mav.MAV_RESULT_UNSUPPORTED
        iv = self.intervals.get(msg_id, 0.0)
        self._interval_reply = (msg_id, int(iv * 1e6) if iv > 0 else -1)
        self._after_ack.append(-1)
        return mav.MAV_RESULT_ACCEPTED

    def _cmd_request_message(self, p, _xy) -> int:
        """MAV_CMD_REQUEST_MESSAGE for any message the emulator produces."""
        msg_id = int(p[0])
        if msg_id not in self.producers:
            return mav.MAV_RESULT_UNSUPPORTED
        self._after_ack.append(msg_id)
        return mav.MAV_RESULT_ACCEPTED

    def _cmd_request_autopilot_capabilities(self, p, _xy) -> int:
        """MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES: AUTOPILOT_VERSION after the ACK."""
        self._after_ack.append(mav.MAVLINK_MSG_ID_AUTOPILOT_VERSION)
        return mav.MAV_RESULT_ACCEPTED

    def _cmd_set_home(self, p, _xy) -> int:
        """MAV_CMD_DO_SET_HOME: param1 = 1 uses the current position; other locations are denied."""
        fc = self.v.fc
        if p[0] >= 0.5 and fc.last_state is not None:
            fc.home = fc.last_state.pos.copy()
            return mav.MAV_RESULT_ACCEPTED
        return mav.MAV_RESULT_DENIED

    def _cmd_condition_yaw(self, p, _xy) -> int:
        """MAV_CMD_CONDITION_YAW: absolute or relative heading for the hold setpoint."""
        fc = self.v.fc
        if not math.isfinite(p[0]) or fc.hold.pos is None:
            return mav.MAV_RESULT_DENIED
        yaw_ned = math.radians(p[0])
        if p[3] >= 0.5 and fc.last_state is not None:
            direction = -1.0 if p[2] < 0 else 1.0
            yaw_ned = euler_zyx(enu_flu_to_ned_frd(fc.last_state.rot))[2] + direction * yaw_ned
        fc.hold.yaw = wrap_pi(math.pi / 2 - yaw_ned)
        return mav.MAV_RESULT_ACCEPTED


def _rotate_keeping_unset(rz: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Rotate a body-frame vector about z; unset (NaN) components stay unset, horizontal as a pair."""
    out = rz @ np.nan_to_num(v)
    if np.isnan(v[:2]).all():
        out[:2] = math.nan
    if math.isnan(v[2]):
        out[2] = math.nan
    return out


def _param_name(raw) -> str:
    """A parameter id as sent (bytes or str, NUL padded) to a clean string."""
    if isinstance(raw, bytes):
        raw = raw.decode("ascii", "replace")
    return str(raw).split("\x00", 1)[0].strip()


COMMANDS = {
    mav.MAV_CMD_COMPONENT_ARM_DISARM: MavlinkLink._cmd_arm,
    mav.MAV_CMD_NAV_TAKEOFF: MavlinkLink._cmd_takeoff,
    mav.MAV_CMD_NAV_LAND: MavlinkLink._cmd_land,
    mav.MAV_CMD_NAV_RETURN_TO_LAUNCH: MavlinkLink._cmd_rtl,
    mav.MAV_CMD_DO_SET_MODE: MavlinkLink._cmd_set_mode,
    mav.MAV_CMD_MISSION_START: MavlinkLink._cmd_mission_start,
    mav.MAV_CMD_DO_REPOSITION: MavlinkLink._cmd_reposition,
    mav.MAV_CMD_DO_CHANGE_SPEED: MavlinkLink._cmd_change_speed,
    mav.MAV_CMD_SET_MESSAGE_INTERVAL: MavlinkLink._cmd_set_message_interval,
    mav.MAV_CMD_GET_MESSAGE_INTERVAL: MavlinkLink._cmd_get_message_interval,
    mav.MAV_CMD_REQUEST_MESSAGE: MavlinkLink._cmd_request_message,
    mav.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES: MavlinkLink._cmd_request_autopilot_capabilities,
    mav.MAV_CMD_DO_SET_HOME: MavlinkLink._cmd_set_home,
    mav.MAV_CMD_CONDITION_YAW: MavlinkLink._cmd_condition_yaw,
}
MavlinkLink.commands = COMMANDS

"""The emulated flight controller of one vehicle: PX4-like modes, arming, setpoints, mission execution."""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np

from firmware_sim import control
from firmware_sim.collision import ObstacleBins, constrain_velocity
from firmware_sim.control import Airframe, Gains
from firmware_sim.frames import wrap_pi, yaw_of

# PX4 custom main modes and AUTO sub modes (px4_custom_mode.h)
MAIN_MANUAL, MAIN_ALTCTL, MAIN_POSCTL, MAIN_AUTO, MAIN_ACRO, MAIN_OFFBOARD, MAIN_STABILIZED = (
    1,
    2,
    3,
    4,
    5,
    6,
    7,
)
SUB_READY, SUB_TAKEOFF, SUB_LOITER, SUB_MISSION, SUB_RTL, SUB_LAND = 1, 2, 3, 4, 5, 6

# MAVLink commands understood by the mission executor
NAV_WAYPOINT, NAV_LOITER_TIME, NAV_RTL, NAV_LAND, NAV_TAKEOFF, DO_CHANGE_SPEED = 16, 19, 20, 21, 22, 178

OFFBOARD_TIMEOUT_WALL_S = 0.5
PREFLIGHT_DISARM_S = 10.0
LANDED_SPEED_M_S = 0.12
CRASH_TILT_RAD = math.radians(70)


@dataclass
class Setpoint:
    """A local-ENU setpoint: position and/or velocity, yaw or yaw rate (None = not controlled)."""

    pos: np.ndarray | None = None
    vel: np.ndarray | None = None
    yaw: float | None = None
    yaw_rate: float | None = None


@dataclass
class NavTarget:
    """One executable mission step in the local ENU frame."""

    seq: int
    command: int
    pos: np.ndarray | None = None
    hold_s: float = 0.0
    speed: float | None = None


@dataclass
class EstimatedState:
    """The state the controller acts on (local ENU estimate) and the true body rates."""

    pos: np.ndarray
    rot: np.ndarray
    vel: np.ndarray
    omega_body: np.ndarray


@dataclass
class FlightController:
    """Mode logic and the cascaded controller for one vehicle; all positions in its local ENU estimate."""

    airframe: Airframe = field(default_factory=Airframe)
    gains: Gains = field(default_factory=Gains)
    params: dict = field(default_factory=dict)
    armed: bool = False
    main_mode: int = MAIN_AUTO
    sub_mode: int = SUB_LOITER
    landed: bool = True
    home: np.ndarray = field(default_factory=lambda: np.zeros(3))
    hold: Setpoint = field(default_factory=Setpoint)
    offboard: Setpoint = field(default_factory=Setpoint)
    offboard_wall: float = -1e9
    mission: list[NavTarget] = field(default_factory=list)
    mission_index: int = 0
    mission_hold_until: float | None = None
    reached_events: list[int] = field(default_factory=list)
    messages: list[tuple[int, str]] = field(default_factory=list)
    cruise_speed: float | None = None
    yaw_sp: float = 0.0
    vel_integral: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])
    armed_at: float = 0.0
    mode_since: float = 0.0
    slow_since: float | None = None
    last_state: EstimatedState | None = None
    last_force: np.ndarray = field(default_factory=lambda: np.zeros(3))
    obstacles: ObstacleBins | None = None
    """The newest OBSTACLE_DISTANCE as body bins (collision prevention, CP_DIST)."""
    cp_cut_steps: int = 0
    """Control steps in which collision prevention cut the horizontal velocity setpoint."""
    now: float = 0.0

    # ------------------------------------------------------------------ commands (return MAV_RESULT)

    def param(self, name: str, default: float) -> float:
        """Current value of a tunable parameter."""
        return float(self.params.get(name, default))

    def arm(self, t: float) -> int:
        """Arm the motors (on the ground or not); 0 = MAV_RESULT_ACCEPTED."""
        if not self.armed:
            self.armed, self.armed_at = True, t
            self.vel_integral = [0.0, 0.0, 0.0]
            if self.last_state is not None:
                self.home = self.last_state.pos.copy()
                self.yaw_sp = yaw_of(self.last_state.rot)
            self._set_mode(MAIN_AUTO, SUB_LOITER, t)
            self._hold_here()
            self.messages.append((6, "Armed by external command"))
        return 0

    def disarm(self, t: float, force: bool = False) -> int:
        """Disarm; refused (1 = TEMPORARILY_REJECTED) in the air unless forced."""
        if self.armed and not self.landed and not force:
            return 1
        self.armed = False
        self.messages.append((6, "Disarmed"))
        return 0

    def set_mode(self, main: int, sub: int, t: float) -> int:
        """Switch flight mode like PX4's commander; 0 accepted, 1 rejected, 2 denied, 3 unsupported."""
        if main in (MAIN_MANUAL, MAIN_ALTCTL, MAIN_POSCTL, MAIN_STABILIZED, MAIN_ACRO):
            self._set_mode(main, 0, t)
            self._hold_here()
            return 0
        if main == MAIN_OFFBOARD:
            if time.monotonic() - self.offboard_wall > OFFBOARD_TIMEOUT_WALL_S:
                return 1
            self._set_mode(MAIN_OFFBOARD, 0, t)
            return 0
        if main != MAIN_AUTO:
            return 3
        if sub == SUB_TAKEOFF:
            return self.takeoff(t, None)
        if sub == SUB_LAND:
            return self.land(t)
        if sub == SUB_RTL:
            return self.return_to_launch(t)
        if sub == SUB_MISSION:
            return self.start_mission(t, self.mission_index)
        if sub in (SUB_LOITER, SUB_READY):
            self._set_mode(MAIN_AUTO, SUB_LOITER, t)
            self._hold_here()
            return 0
        return 3

    def takeoff(self, t: float, altitude_rel: float | None) -> int:
        """Climb to the takeoff altitude above home (MIS_TAKEOFF_ALT unless given); needs arming."""
        if not self.armed:
            return 2
        alt = self.param("MIS_TAKEOFF_ALT", 2.5) if altitude_rel is None else float(altitude_rel)
        if not (0.1 <= alt <= 100.0):
            return 2
        here = self.last_state.pos if self.last_state is not None else self.home
        self.hold = Setpoint(pos=np.array([here[0], here[1], self.home[2] + alt]), yaw=self.yaw_sp)
        self._set_mode(MAIN_AUTO, SUB_TAKEOFF, t)
        return 0

    def land(self, t: float) -> int:
        """Descend where the vehicle is and disarm on touchdown."""
        if not self.armed:
            return 2
        if self.last_state is not None:  # land where it is now, not at an older hold point
            self.hold = Setpoint(pos=self.last_state.pos.copy(), yaw=self.yaw_sp)
        self._set_mode(MAIN_AUTO, SUB_LAND, t)
        self.slow_since = None
        return 0

    def return_to_launch(self, t: float) -> int:
        """Fly back above home at the current altitude, then land."""
        if not self.armed:
            return 2
        self._set_mode(MAIN_AUTO, SUB_RTL, t)
        return 0

    def reposition(self, t: float, pos: np.ndarray, yaw: float | None) -> int:
        """Go to a point and hold there (DO_REPOSITION)."""
        if not self.armed or not np.all(np.isfinite(pos)):
            return 2
        self.hold = Setpoint(pos=np.asarray(pos, float), yaw=self.yaw_sp if yaw is None else yaw)
        self._set_mode(MAIN_AUTO, SUB_LOITER, t)
        self.landed = False if pos[2] > self.home[2] + 0.2 else self.landed
        return 0

    def set_offboard_setpoint(self, sp: Setpoint) -> None:
        """Store the latest offboard setpoint (stream it at >= 2 Hz to enter/keep OFFBOARD)."""
        self.offboard = sp
        self.offboard_wall = time.monotonic()

    def load_mission(self, targets: list[NavTarget]) -> None:
        """Replace the mission with executable targets."""
        self.mission = list(targets)
        self.mission_index = 0

    def start_mission(self, t: float, first: int = 0) -> int:
        """Start (or resume) the mission at item `first`; needs arming and a non-empty mission."""
        if not self.armed or not self.mission:
            return 2
        self.mission_index = max(0, min(int(first), len(self.mission) - 1))
        self.mission_hold_until = None
        self._set_mode(MAIN_AUTO, SUB_MISSION, t)
        return 0

    # ------------------------------------------------------------------ periodic logic

    def flight_status(self) -> int:
        """MAV_LANDED_STATE: 1 on ground, 2 in air, 3 taking off, 4 landing."""
        if self.landed or not self.armed:
            return 1
        if self.main_mode == MAIN_AUTO and self.sub_mode == SUB_TAKEOFF:
            return 3
        if self.main_mode == MAIN_AUTO and self.sub_mode == SUB_LAND:
            return 4
        return 2

    def update(self, t: float, dt: float, s: EstimatedState) -> tuple[np.ndarray, np.ndarray]:
        """Advance the mode logic and return (force in local ENU, torque in body FLU) for this step."""
        self.last_state = s
        self.now = t
        if not self.armed:
            self.landed = True
            return np.zeros(3), np.zeros(3)
        if s.rot[2, 2] < math.cos(CRASH_TILT_RAD):
            self.armed = False
            self.messages.append((2, "Crash detected: disarmed"))
            return np.zeros(3), np.zeros(3)
        sp = self._mode_setpoint(t, dt, s)
        if self.landed:
            if not self._wants_to_climb(s, sp):
                self.vel_integral = [0.0, 0.0, 0.0]
                if self.armed and t - self.armed_at > self.param("COM_DISARM_PRFLT", PREFLIGHT_DISARM_S):
                    self.armed = False
                    self.messages.append((6, "Disarmed: no takeoff"))
                return np.zeros(3), np.zeros(3)
            self.landed = False
        return self._control(dt, s, sp)

    def _wants_to_climb(self, s: EstimatedState, sp: Setpoint) -> bool:
        """True if the active setpoint asks the vehicle on the ground to lift off."""
        if sp.pos is not None and sp.pos[2] > s.pos[2] + 0.15:
            return True
        return sp.vel is not None and sp.vel[2] > 0.1

    def _mode_setpoint(self, t: float, dt: float, s: EstimatedState) -> Setpoint:
        """The setpoint of the active mode, switching modes on completion like PX4's navigator."""
        if self.main_mode == MAIN_OFFBOARD:
            if time.monotonic() - self.offboard_wall > OFFBOARD_TIMEOUT_WALL_S:
                self.messages.append((4, "Offboard setpoints lost: holding"))
                self._set_mode(MAIN_AUTO, SUB_LOITER, t)
                self._hold_here()
                return self.hold
            return self.offboard
        if self.main_mode == MAIN_AUTO and self.sub_mode == SUB_TAKEOFF:
            if abs(s.pos[2] - self.hold.pos[2]) < 0.15:
                self._set_mode(MAIN_AUTO, SUB_LOITER, t)
            return self.hold
        if self.main_mode == MAIN_AUTO and self.sub_mode == SUB_LAND:
            return self._landing(t, s)
        if self.main_mode == MAIN_AUTO and self.sub_mode == SUB_RTL:
            target = np.array([self.home[0], self.home[1], s.pos[2]])
            if np.linalg.norm(target[:2] - s.pos[:2]) < self.param("NAV_ACC_RAD", 0.3):
                self.land(t)
                return self._landing(t, s)
            return Setpoint(pos=target, yaw=self._heading_to(s, target))
        if self.main_mode == MAIN_AUTO and self.sub_mode == SUB_MISSION:
            return self._mission_setpoint(t, s)
        return self.hold

    def _landing(self, t: float, s: EstimatedState) -> Setpoint:
        """Descend at MPC_LAND_SPEED; disarm after resting still on something for 0.5 s."""
        if abs(s.vel[2]) < LANDED_SPEED_M_S and t - self.mode_since > 1.0:
            self.slow_since = t if self.slow_since is None else self.slow_since
            if t - self.slow_since > 0.5:
                self.landed, self.armed = True, False
                self.messages.append((6, "Landing detected: disarmed"))
        else:
            self.slow_since = None
        xy = self.hold.pos if self.hold.pos is not None else s.pos
        v = np.array([0.0, 0.0, -self.param("MPC_LAND_SPEED", 0.7)])
        return Setpoint(pos=np.array([xy[0], xy[1], np.nan]), vel=v, yaw=self.yaw_sp)

    def _mission_setpoint(self, t: float, s: EstimatedState) -> Setpoint:
        """Execute the current mission item, emitting MISSION_ITEM_REACHED events as items complete."""
        while self.mission_index < len(self.mission):
            item = self.mission[self.mission_index]
            if item.command == DO_CHANGE_SPEED:
                self.cruise_speed = item.speed
                self._advance(item)
                continue
            if item.command == NAV_TAKEOFF:
                alt = item.pos[2] if item.pos is not None else self.param("MIS_TAKEOFF_ALT", 2.5)
                target = (
                    np.array([s.pos[0], s.pos[1], alt])
                    if self.landed or self.hold.pos is None
                    else np.array([self.hold.pos[0], self.hold.pos[1], alt])
                )
                self.hold = Setpoint(pos=target, yaw=self.yaw_sp)
                if abs(s.pos[2] - alt) < 0.2:
                    self._advance(item)
                    continue
                return self.hold
            if item.command == NAV_LAND:
                if item.pos is not None and np.linalg.norm(item.pos[:2] - s.pos[:2]) > 0.3:
                    target = np.array([item.pos[0], item.pos[1], s.pos[2]])
                    return Setpoint(pos=target, yaw=self._heading_to(s, target))
                self._advance(item)
                self.hold = Setpoint(pos=s.pos.copy(), yaw=self.yaw_sp)
                self.land(t)
                return self._landing(t, s)
            if item.command == NAV_RTL:
                self._advance(item)
                self.return_to_launch(t)
                return self.hold
            if item.command in (NAV_WAYPOINT, NAV_LOITER_TIME) and item.pos is not None:
                target = item.pos.copy()
                if s.pos[2] < self.home[2] + 0.5 and target[2] > s.pos[2] + 0.3:
                    # PX4-like implicit takeoff: climb vertically before heading off on the ground.
                    h = self.hold.pos
                    climbing = h is not None and h[2] == target[2] and np.linalg.norm(h[:2] - s.pos[:2]) < 0.5
                    if not climbing:  # fix the climb's xy once, then hold it
                        self.hold = Setpoint(pos=np.array([s.pos[0], s.pos[1], target[2]]), yaw=self.yaw_sp)
                    if self.landed or np.linalg.norm(target[:2] - s.pos[:2]) > 0.5:
                        return self.hold
                if np.linalg.norm(target - s.pos) < self.param("NAV_ACC_RAD", 0.3):
                    if self.mission_hold_until is None:
                        self.mission_hold_until = t + item.hold_s
                    if t >= self.mission_hold_until:
                        self.mission_hold_until = None
                        self._advance(item)
                        continue
                self.hold = Setpoint(pos=target, yaw=self._heading_to(s, target))
                return self.hold
            self._advance(item)
        return self.hold

    def _advance(self, item: NavTarget) -> None:
        """Mark a mission item reached and move to the next one."""
        self.reached_events.append(item.seq)
        self.mission_index += 1

    def _heading_to(self, s: EstimatedState, target: np.ndarray) -> float:
        """Yaw facing the target horizontally, or the current yaw setpoint when already there."""
        d = target[:2] - s.pos[:2]
        return math.atan2(d[1], d[0]) if math.hypot(d[0], d[1]) > 0.5 else self.yaw_sp

    def reframe(self, transform: np.ndarray) -> None:
        """The estimate's frame changed (estimator re-initialised or reset): carry every local-frame
        target (home, hold, offboard setpoint, mission items) and heading by the 4x4 from the old frame
        into the new one, so the vehicle keeps flying where it was going."""
        rot, shift = transform[:3, :3], transform[:3, 3]
        turn = yaw_of(rot)

        def move(p):
            if p is None:
                return None
            p = np.asarray(p, float)
            unset = np.isnan(p)
            out = rot @ np.nan_to_num(p) + shift
            out[unset] = math.nan
            return out

        self.home = move(self.home)
        for sp in (self.hold, self.offboard):
            sp.pos = move(sp.pos)
            sp.vel = None if sp.vel is None else rot @ np.asarray(sp.vel, float)
            sp.yaw = None if sp.yaw is None else wrap_pi(sp.yaw + turn)
        for item in self.mission:
            item.pos = move(item.pos)
        self.yaw_sp = wrap_pi(self.yaw_sp + turn)
        self.last_state = None

    def hold_through(self, t: float) -> tuple[int, int]:
        """Hold the current position (the emulator's stand-in for a flight controller that is
        rebooting); returns the mode to resume."""
        mode = (self.main_mode, self.sub_mode)
        if self.armed and not self.landed:
            self._set_mode(MAIN_AUTO, SUB_LOITER, t)
            self._hold_here()
        return mode

    def resume(self, mode: tuple[int, int], t: float) -> None:
        """Back to a mode held through a reboot (a mission continues from its current item)."""
        if self.armed and mode[0] == MAIN_AUTO and mode[1] == SUB_MISSION:
            self._set_mode(*mode, t)

    def _set_mode(self, main: int, sub: int, t: float) -> None:
        """Enter a mode, remembering when."""
        if (main, sub) != (self.main_mode, self.sub_mode):
            self.mode_since = t
        self.main_mode, self.sub_mode = main, sub

    def _hold_here(self) -> None:
        """Hold the current estimated position and heading."""
        if self.last_state is not None:
            self.hold = Setpoint(pos=self.last_state.pos.copy(), yaw=yaw_of(self.last_state.rot))
            self.yaw_sp = self.hold.yaw

    # ------------------------------------------------------------------ control

    def _prevent_collision(self, vel_sp: list[float], vel: list[float], rot) -> list[float]:
        """PX4-style collision prevention (firmware_sim.collision) in position-controlled and offboard
        flight with CP_DIST > 0: the horizontal setpoint toward near or unknown sectors is cut."""
        cp_dist = self.param("CP_DIST", -1.0)
        if cp_dist <= 0 or self.main_mode not in (MAIN_OFFBOARD, MAIN_POSCTL):
            return vel_sp
        yaw = math.atan2(rot[1][0], rot[0][0])
        xy, cut = constrain_velocity(vel_sp[:2], vel[:2], yaw, self.obstacles, self.now, cp_dist,
                                     self.param("CP_DELAY", 0.4), self.param("CP_GO_NO_DATA", 0) >= 1)
        if not cut:
            return vel_sp
        self.cp_cut_steps += 1
        return [float(xy[0]), float(xy[1]), vel_sp[2]]

    def _control(self, dt: float, s: EstimatedState, sp: Setpoint) -> tuple[np.ndarray, np.ndarray]:
        """Run the cascade for a setpoint; NaN position components fall back to velocity control."""
        g = self.gains
        pos, vel, rot, omega = s.pos.tolist(), s.vel.tolist(), s.rot.tolist(), s.omega_body.tolist()
        vel_sp = [0.0] * 3 if sp.vel is None else [float(x) if math.isfinite(x) else 0.0 for x in sp.vel]
        if sp.pos is not None:
            pos_sp = [float(x) for x in sp.pos]
            known = [math.isfinite(x) for x in pos_sp]
            cruise = self.cruise_speed or self.param("MPC_XY_CRUISE", g.max_speed_xy)
            target = [pos_sp[k] if known[k] else pos[k] for k in range(3)]
            v_pos = control.velocity_setpoint(pos, target, g, cruise)
            feed = sp.vel is not None
            vel_sp = [(v_pos[k] + (vel_sp[k] if feed else 0.0)) if known[k] else vel_sp[k] for k in range(3)]
        vel_sp = self._prevent_collision(vel_sp, vel, rot)
        if sp.yaw_rate is not None and math.isfinite(sp.yaw_rate):
            self.yaw_sp = wrap_pi(self.yaw_sp + max(-g.max_yaw_rate, min(g.max_yaw_rate, sp.yaw_rate)) * dt)
        elif sp.yaw is not None and math.isfinite(sp.yaw):
            self.yaw_sp = control.slew_yaw(self.yaw_sp, sp.yaw, g.max_yaw_rate, dt)
        self.vel_integral = [
            min(2.0, max(-2.0, self.vel_integral[k] + (vel_sp[k] - vel[k]) * dt)) for k in range(3)
        ]
        force = control.thrust_vector(vel, vel_sp, self.vel_integral, self.airframe, g)
        torque = control.attitude_torque(rot, force, self.yaw_sp, omega, self.airframe, g)
        thrust = control.collective_thrust(force, rot)
        self.last_force = np.array([thrust * rot[0][2], thrust * rot[1][2], thrust * rot[2][2]])
        return self.last_force, np.array(torque)

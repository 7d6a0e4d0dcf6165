"""The simulator: one MuJoCo model with N quadrotors, paced on one simulated clock, with their I/O."""

from __future__ import annotations

import math
import os
import select
import sys
import threading
import time
from collections import deque
from dataclasses import dataclass, field

import mujoco
import numpy as np

from firmware_sim.camera import CameraConfig, DepthCamera
from firmware_sim.camera_server import CameraPublisher, encode_frame
from firmware_sim.collision import Contact
from firmware_sim.control import Airframe
from firmware_sim.flight import (
    NAV_LAND,
    NAV_TAKEOFF,
    NAV_WAYPOINT,
    EstimatedState,
    FlightController,
    NavTarget,
)
from firmware_sim.frames import mat_to_quat, quat_to_mat, rot_z, yaw_of
from firmware_sim.mavlink_link import take_vehicle_events
from firmware_sim.odometry import NOISE_PRESETS, NoiseConfig, OdometryModel
from firmware_sim.worlds import World, compose_mjcf

PHYSICS_DT = 0.004
CONTROL_EVERY = 2
TRAJECTORY_EVERY = 10
MAX_STEPS_PER_BATCH = 25
MAX_LAG_WALL_S = 0.25  # behind real time x speed by more than this: re-anchor the pacing
MAX_CONTACTS_LOGGED = 1000
FLOOR_PREFIX = "floor"
"""World geoms named so are the ground: resting or landing on them is no collision."""
DEFAULT_CAMERA = CameraConfig()


def vehicle_mjcf(i: int, pose, airframe: Airframe) -> str:
    """The <body> of quadrotor i at a start pose (x, y, z, yaw): a box frame with arms, 1.5 kg."""
    x, y, z, yaw = pose
    hx, hy, hz = airframe.half_extent
    ix, iy, iz = airframe.inertia
    qw, qz = math.cos(yaw / 2), math.sin(yaw / 2)
    return (
        f'<body name="quad{i}" pos="{x:.4f} {y:.4f} {z + hz + 0.005:.4f}" quat="{qw:.6f} 0 0 {qz:.6f}">'
        f'<freejoint name="quad{i}_free"/>'
        f'<inertial pos="0 0 0" mass="{airframe.mass}" diaginertia="{ix} {iy} {iz}"/>'
        f'<geom name="quad{i}_body" type="box" size="0.08 0.08 {hz:.3f}" rgba="0.1 0.1 0.6 1" mass="0"/>'
        f'<geom name="quad{i}_arm1" type="box" size="{hx:.3f} 0.015 0.01" euler="0 0 45" mass="0"/>'
        f'<geom name="quad{i}_arm2" type="box" size="{hy:.3f} 0.015 0.01" euler="0 0 -45" mass="0"/>'
        "</body>"
    )


@dataclass
class Vehicle:
    """One simulated quadrotor: physics body, flight controller, estimator model, camera, log."""

    index: int
    body_id: int
    qpos_adr: int
    qvel_adr: int
    true_start_pose: tuple[float, float, float, float]
    fc: FlightController
    odometry: OdometryModel
    camera: DepthCamera | None
    publisher: CameraPublisher | None = None
    link: object | None = None
    """The onboard/API MAVLink instance (sends to mavlink_base_port + index)."""
    gcs_link: object | None = None
    """The GCS MAVLink instance (sends to gcs_port), if the simulation has one."""
    autopilot_state: dict = field(default_factory=dict)
    """Per-vehicle state an autopilot personality shares between its instances (mode, parameters)."""
    camera_seq: int = 0
    next_frame_t: float = 0.0
    trajectory: list[tuple[float, float, float, float, float, float, float, float]] = field(
        default_factory=list
    )
    camera_path: str | None = None
    camera_stalled_until: float = 0.0
    """Wall-clock (monotonic) time until which the camera publishes nothing (a stall fault)."""
    frames_withheld: int = 0
    """Frames the camera took but did not publish because it was stalled."""
    contacts: list[Contact] = field(default_factory=list)
    """The first MAX_CONTACTS_LOGGED contacts of the body with anything but the floor."""
    contact_count: int = 0
    """Contacts begun with anything but the floor (each geom touched anew counts once)."""
    touching: set[int] = field(default_factory=set)
    boot_offset: float = 0.0
    """Sim time at which the flight controller last booted: its MAVLink stamps count from there."""
    fc_down_until: float = -math.inf
    """Sim time until which the flight controller reboots (MAVLink silent); see Simulation.reboot_fc."""
    fc_reboots: int = 0
    pending_restart: tuple | None = None
    """(keep_origin, frame turn, mode to resume) of a reboot in progress."""

    sim: Simulation | None = field(default=None, repr=False)

    @property
    def system_id(self) -> int:
        """MAVLink system id (index + 1)."""
        return self.index + 1

    def true_pose(self) -> tuple[np.ndarray, np.ndarray]:
        """True world position and quaternion (w, x, y, z)."""
        return self.sim.true_pose(self.index)

    def true_trajectory(self) -> np.ndarray:
        """Logged true trajectory: rows (t, x, y, z, qw, qx, qy, qz)."""
        return self.sim.trajectory(self.index)

    def fc_rebooting(self, t: float) -> bool:
        """True while the flight controller reboots (its MAVLink endpoint is silent)."""
        return t < self.fc_down_until

    @property
    def links(self) -> list:
        """Every MAVLink instance of the vehicle (onboard/API first)."""
        return [k for k in (self.link, self.gcs_link) if k is not None]

    @property
    def mavlink_endpoint(self) -> tuple[str, int] | None:
        """(host, port) the vehicle's MAVLink socket is bound to, if MAVLink is on."""
        return None if self.link is None else (self.link.bind_host, self.link.bound_port)


class Simulation:
    """N quadrotors in a world, stepped at 250 Hz of simulated time, paced to real time x speed."""

    def __init__(
        self,
        world: World,
        n_vehicles: int = 1,
        seed: int = 0,
        speed: float = 1.0,
        noise: str | NoiseConfig = "default",
        camera: CameraConfig | None = DEFAULT_CAMERA,
        start_poses=None,
        frame: str = "start",
        mavlink: bool = True,
        mavlink_base_port: int = 14540,
        mavlink_hosts: list[str] | None = None,
        mavlink_bind_host: str | list[str] = "127.0.0.1",
        camera_dir: str | None = None,
        camera_tcp_base_port: int | None = None,
        route: str | None = None,
        gcs_port: int | None = None,
        autopilot: str = "px4",
    ):
        if not (1 <= n_vehicles <= 64):
            raise ValueError("n_vehicles must be within 1..64")
        if not (0 < speed <= 1000):
            raise ValueError("speed must be within (0, 1000]")
        if frame not in ("start", "world"):
            raise ValueError("frame is 'start' (each vehicle's start pose) or 'world'")
        if autopilot not in AUTOPILOTS:
            raise ValueError(f"autopilot is one of {sorted(AUTOPILOTS)}")
        if gcs_port is not None and not 1 <= gcs_port <= 65535:
            raise ValueError("gcs_port must be within 1..65535")
        self.autopilot = autopilot
        self.world, self.seed, self.speed, self.frame = world, int(seed), float(speed), frame
        noise_cfg = NOISE_PRESETS[noise] if isinstance(noise, str) else noise
        poses = list(start_poses) if start_poses is not None else world.start_poses(n_vehicles)
        if len(poses) != n_vehicles:
            raise ValueError("need one start pose per vehicle")
        self.airframe = Airframe()
        bodies = "\n    ".join(vehicle_mjcf(i, p, self.airframe) for i, p in enumerate(poses))
        self.model = mujoco.MjModel.from_xml_string(compose_mjcf(world, bodies, PHYSICS_DT))
        self.data = mujoco.MjData(self.model)
        mujoco.mj_forward(self.model, self.data)
        self.time = 0.0
        self.steps = 0
        self.lock = threading.RLock()
        self._thread: threading.Thread | None = None
        self._render_thread: threading.Thread | None = None
        self._render_jobs: deque = deque()
        self._render_cv = threading.Condition()
        self.failure: Exception | None = None
        self.frame_sink = None  # optional callable(vehicle_index, header, z16) for in-process consumers
        self._running = False
        self.wall_started = 0.0
        self.lag_s = 0.0  # wall seconds behind the requested pace at the last check
        self.lag_resets = 0  # times the pacing gave up catching up (machine too slow for --speed)
        self.vehicles: list[Vehicle] = []
        root = np.random.SeedSequence(self.seed)
        for i, ss in enumerate(root.spawn(n_vehicles)):
            rng_odo, rng_cam = (np.random.default_rng(s) for s in ss.spawn(2))
            body = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_BODY, f"quad{i}")
            jnt = self.model.body_jntadr[body]
            # The pose as MuJoCo placed it (the MJCF text rounds), so frames start exactly at zero.
            x, y = (float(c) for c in self.data.xpos[body][:2])
            yaw = yaw_of(self.data.xmat[body].reshape(3, 3))
            # The reporting frame is ENU-like; MAVLink NED is its x/y swap, so a frame yawed by
            # (heading - 90 deg) reports x along the initial heading, like VIO without a compass.
            if frame == "start":
                odo = OdometryModel((x, y, 0.0), yaw - math.pi / 2, noise_cfg, rng_odo)
            else:
                odo = OdometryModel((0.0, 0.0, 0.0), 0.0, noise_cfg, rng_odo)
            cam = DepthCamera(self.model, body, camera, rng_cam) if camera is not None else None
            v = Vehicle(
                i,
                body,
                int(self.model.jnt_qposadr[jnt]),
                int(self.model.jnt_dofadr[jnt]),
                (x, y, float(self.data.xpos[body][2]), yaw),
                FlightController(params=default_params(i)),  # PX4 names: the FC's own tuning keys
                odo,
                cam,
            )
            v.sim = self
            self.vehicles.append(v)
        names = [mujoco.mj_id2name(self.model, mujoco.mjtObj.mjOBJ_GEOM, g) or f"geom{g}"
                 for g in range(self.model.ngeom)]
        self._geom_names = names
        self._geom_ground = [n.startswith(FLOOR_PREFIX) for n in names]
        owner_of_body = {v.body_id: v.index for v in self.vehicles}
        self._geom_owner = [owner_of_body.get(int(b), -1) for b in self.model.geom_bodyid]
        """Vehicle index per geom (-1: the world's); plain lists, read at every physics step."""
        self._touching_any = False
        if mavlink_hosts is not None and len(mavlink_hosts) != n_vehicles:
            raise ValueError("need one MAVLink host per vehicle")
        if not isinstance(mavlink_bind_host, str) and len(mavlink_bind_host) != n_vehicles:
            raise ValueError("mavlink_bind_host is one address, or one per vehicle")
        self._setup_io(mavlink, mavlink_base_port, mavlink_hosts, mavlink_bind_host, camera_dir,
                       camera_tcp_base_port, gcs_port)
        self._record_all()
        if route == "builtin":
            self.fly_builtin_routes()
        elif route is not None:
            raise ValueError("route is None or 'builtin'")

    # ------------------------------------------------------------------ wiring

    def _setup_io(self, mavlink: bool, base_port: int, hosts: list[str] | None, bind_host: str | list[str],
                  camera_dir: str | None, tcp_base: int | None, gcs_port: int | None) -> None:
        """Open each vehicle's MAVLink instances (bound on bind_host, or bind_host[i] when each vehicle
        has its own wire): onboard/API sending to hosts[i]:base_port+i (default loopback) and, with
        gcs_port, a GCS instance sending to hosts[i]:gcs_port, as PX4 SITL does; and the camera publisher."""
        if mavlink:
            from firmware_sim.mavlink_link import GCS_RATES_HZ

            link_class = AUTOPILOTS[self.autopilot]()
            for v in self.vehicles:
                host = "127.0.0.1" if hosts is None else hosts[v.index]
                bind = bind_host if isinstance(bind_host, str) else bind_host[v.index]
                v.link = link_class(self, v, (host, base_port + v.index), bind_host=bind, instance=0)
                if gcs_port is not None:
                    gcs_rates = GCS_RATES_HZ if self.autopilot == "px4" else None
                    v.gcs_link = link_class(self, v, (host, gcs_port), bind_host=bind, rates=gcs_rates,
                                            instance=1)
        if camera_dir is not None:
            os.makedirs(camera_dir, exist_ok=True)
        for v in self.vehicles:
            if v.camera is None or (camera_dir is None and tcp_base is None):
                continue
            path = os.path.join(camera_dir, f"camera{v.index}.sock") if camera_dir else None
            v.publisher = CameraPublisher(path, None if tcp_base is None else tcp_base + v.index)
            v.camera_path = path

    def endpoints(self) -> list[dict]:
        """Where each vehicle can be reached: MAVLink ports, system id, camera socket."""
        out = []
        for v in self.vehicles:
            e = {"vehicle": v.index, "system_id": v.system_id, "start_pose": list(v.true_start_pose)}
            if v.link is not None:
                e["autopilot"] = self.autopilot
                e["mavlink_bound"] = f"udp://{v.link.bind_host}:{v.link.bound_port}"
                e["mavlink_target"] = f"udp://{v.link.target[0]}:{v.link.target[1]}"
            if v.gcs_link is not None:
                e["mavlink_gcs_bound"] = f"udp://{v.gcs_link.bind_host}:{v.gcs_link.bound_port}"
                e["mavlink_gcs_target"] = f"udp://{v.gcs_link.target[0]}:{v.gcs_link.target[1]}"
            if v.publisher is not None:
                e["camera_unix"] = v.publisher.unix_path
                e["camera_tcp"] = (
                    None if v.publisher.tcp_port is None else f"127.0.0.1:{v.publisher.tcp_port}"
                )
            out.append(e)
        return out

    # ------------------------------------------------------------------ truth for tests

    def vehicle(self, i: int) -> Vehicle:
        """The i-th vehicle (0-based)."""
        return self.vehicles[i]

    def true_pose(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """True world position and quaternion (w, x, y, z) of vehicle i."""
        v = self.vehicles[i]
        with self.lock:
            q = self.data.qpos[v.qpos_adr : v.qpos_adr + 7].copy()
        return q[:3], q[3:]

    def place_vehicle(self, i: int, pos, yaw: float = 0.0) -> None:
        """Teleport vehicle i (at rest, level, given heading) for tests; updates derived quantities."""
        v = self.vehicles[i]
        with self.lock:
            self.data.qpos[v.qpos_adr : v.qpos_adr + 3] = pos
            self.data.qpos[v.qpos_adr + 3 : v.qpos_adr + 7] = [math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)]
            self.data.qvel[v.qvel_adr : v.qvel_adr + 6] = 0.0
            mujoco.mj_forward(self.model, self.data)

    def reboot_fc(self, i: int, downtime_s: float = 2.0, move_origin: bool = True,
                  turn_rad: float = 0.0) -> None:
        """Reboot vehicle i's flight controller in flight: its MAVLink endpoint goes silent for
        downtime_s (simulated), then comes back with time since boot restarted at 0, a new message
        sequence and default stream rates; its estimator comes back with the local origin at the
        vehicle's position then (move_origin) and the frame turned by turn_rad (a VIO without compass),
        or in the old frame. Unlike a real multicopter, the emulated airframe holds its position
        through the downtime, then resumes a mission it was flying (targets carried into the new frame).
        The camera stamps frames in the FC's time base, so its stamps restart with it."""
        if not (0.0 <= downtime_s <= 600.0) or not math.isfinite(turn_rad) or abs(turn_rad) > math.pi:
            raise ValueError("downtime_s is 0..600 s, turn_rad within +-pi")
        v = self.vehicles[i]
        with self.lock:
            if v.pending_restart is not None:
                raise RuntimeError(f"vehicle {i}'s flight controller is already rebooting")
            v.fc_down_until = self.time + downtime_s
            v.pending_restart = (not move_origin, float(turn_rad), v.fc.hold_through(self.time))
            v.fc_reboots += 1

    def reset_estimator(self, i: int, shift_m=None, turn_rad: float = 0.0) -> np.ndarray:
        """Vehicle i's estimator resets its position without a reboot (ODOMETRY.reset_counter + 1): the
        reporting frame's origin moves by shift_m (world metres; None: to the vehicle's position now)
        and turns by turn_rad, so the reported pose jumps. Returns the 4x4 from the old local frame
        into the new one."""
        if not math.isfinite(turn_rad) or abs(turn_rad) > math.pi:
            raise ValueError("turn_rad within +-pi")
        v = self.vehicles[i]
        with self.lock:
            odo = v.odometry
            if shift_m is None:
                origin = self.true_pose(i)[0]
            else:
                shift = np.asarray(shift_m, float)
                if shift.shape != (3,) or not np.all(np.isfinite(shift)) or np.abs(shift).max() > 1e4:
                    raise ValueError("shift_m is a finite (x, y, z) within 10 km")
                origin = odo.origin + shift
            return self._reframe(v, origin, odo.frame_yaw + turn_rad, odo.reset_counter + 1)

    def _reframe(self, v: Vehicle, origin, frame_yaw: float, reset_counter: int) -> np.ndarray:
        """Switch v's estimator to a new reporting frame and carry its flight controller's targets."""
        transform = v.odometry.reframe(self.time, origin, frame_yaw, reset_counter)
        v.fc.reframe(transform)
        return transform

    def _restart_fc(self, v: Vehicle) -> None:
        """The end of a reboot: the estimator's new frame, a fresh time base and MAVLink instances."""
        keep_origin, turn, mode = v.pending_restart
        v.pending_restart = None
        odo = v.odometry
        if keep_origin:
            self._reframe(v, odo.origin, odo.frame_yaw, 0)
        else:
            self._reframe(v, self.data.qpos[v.qpos_adr : v.qpos_adr + 3].copy(), odo.frame_yaw + turn, 0)
        v.fc.resume(mode, self.time)
        v.boot_offset = self.time
        for link in v.links:
            link.restart()

    def fc_frame_transform(self, i: int, t_old: float, t_new: float) -> np.ndarray:
        """Truth for tests: the 4x4 carrying points of vehicle i's drift-free reporting frame in use at
        sim time t_new into the one in use at t_old (identity when the estimator kept its frame)."""
        odo = self.vehicles[i].odometry
        (o_old, y_old), (o_new, y_new) = odo.frame_at(t_old), odo.frame_at(t_new)
        out = np.eye(4)
        out[:3, :3] = rot_z(y_old).T @ rot_z(y_new)
        out[:3, 3] = rot_z(y_old).T @ (o_new - o_old)
        return out

    def true_velocity(self, i: int) -> np.ndarray:
        """True world-frame linear velocity of vehicle i."""
        v = self.vehicles[i]
        with self.lock:
            return self.data.qvel[v.qvel_adr : v.qvel_adr + 3].copy()

    def trajectory(self, i: int) -> np.ndarray:
        """Logged true trajectory of vehicle i: rows (t, x, y, z, qw, qx, qy, qz) at 25 Hz."""
        with self.lock:
            return np.array(self.vehicles[i].trajectory)

    def estimated_state(self, v: Vehicle) -> EstimatedState:
        """The noise-free drifting estimate the flight controller acts on."""
        q = self.data.qpos[v.qpos_adr : v.qpos_adr + 7]
        rot_w = quat_to_mat(q[3:])  # from qpos (current), not xmat (kinematics of the previous step)
        vel_w = self.data.qvel[v.qvel_adr : v.qvel_adr + 3]
        omega = self.data.qvel[v.qvel_adr + 3 : v.qvel_adr + 6].copy()
        p, r, vel = v.odometry.estimate(self.time, q[:3], rot_w, vel_w)
        return EstimatedState(p, r, vel, omega)

    # ------------------------------------------------------------------ stepping

    def step(self, seconds: float = PHYSICS_DT) -> None:
        """Advance the simulation by at least `seconds` of simulated time (in-process, no pacing)."""
        if self._thread is not None:
            raise RuntimeError("step() drives the clock in-process; the real-time thread is running")
        n = max(1, int(round(seconds / PHYSICS_DT)))
        for _ in range(n):
            with self.lock:
                self._step_once()
            self._service_io(0.0)

    def _step_once(self) -> None:
        """One physics step: controllers, forces, drag, mj_step, logs, cameras, telemetry."""
        d = self.data
        if self.steps % CONTROL_EVERY == 0:
            for v in self.vehicles:
                v.odometry.set_drifting(self.time, v.fc.armed)  # disarmed on the ground: no drift
                s = self.estimated_state(v)
                force_l, torque_b = v.fc.update(self.time, PHYSICS_DT * CONTROL_EVERY, s)
                force_w = v.odometry.local_to_world_vector(self.time, force_l)
                rot_w = d.xmat[v.body_id].reshape(3, 3)
                v._ctrl = (force_w, rot_w @ torque_b)
        for v in self.vehicles:
            force_w, torque_w = getattr(v, "_ctrl", (np.zeros(3), np.zeros(3)))
            drag = -self.airframe.linear_drag * d.qvel[v.qvel_adr : v.qvel_adr + 3]
            d.xfrc_applied[v.body_id, :3] = force_w + drag
            d.xfrc_applied[v.body_id, 3:] = torque_w
        mujoco.mj_step(self.model, d)
        self.steps += 1
        self.time = self.steps * PHYSICS_DT
        self._record_contacts()
        if self.steps % TRAJECTORY_EVERY == 0:
            self._record_all()
        for v in self.vehicles:
            if v.pending_restart is not None and not v.fc_rebooting(self.time):
                self._restart_fc(v)
            if v.camera is not None and self.time + 1e-9 >= v.next_frame_t:
                v.next_frame_t += 1.0 / v.camera.cfg.rate_hz
                self._capture(v)
            if v.link is not None:
                reached, texts = take_vehicle_events(v.fc)
                for link in v.links:
                    link.on_sim_step(self.time, reached, texts)

    def _record_contacts(self) -> None:
        """Log every contact a vehicle's body begins with a geom that is not the floor (a wall, furniture,
        another vehicle): Vehicle.contact_count, Vehicle.contacts (the first MAX_CONTACTS_LOGGED)."""
        d = self.data
        now: dict[int, set[int]] = {}
        if d.ncon:
            owner, ground = self._geom_owner, self._geom_ground
            for a, b in d.contact.geom.tolist():  # a few pairs: plain Python is cheaper than numpy here
                oa, ob = owner[a], owner[b]
                if oa >= 0 and ob != oa and not ground[b]:
                    now.setdefault(oa, set()).add(b)
                if ob >= 0 and oa != ob and not ground[a]:
                    now.setdefault(ob, set()).add(a)
        if not now and not self._touching_any:
            return
        self._touching_any = bool(now)
        for v in self.vehicles:
            touching = now.get(v.index, set())
            for g in touching - v.touching:
                v.contact_count += 1
                if len(v.contacts) < MAX_CONTACTS_LOGGED:
                    pos = d.qpos[v.qpos_adr : v.qpos_adr + 3]
                    speed = float(np.linalg.norm(d.qvel[v.qvel_adr : v.qvel_adr + 3]))
                    v.contacts.append(Contact(self.time, v.index, self._geom_names[g],
                                              tuple(float(x) for x in pos), speed))
            v.touching = touching

    def contacts(self, i: int) -> list[Contact]:
        """The contacts vehicle i's body began with anything but the floor, oldest first."""
        with self.lock:
            return list(self.vehicles[i].contacts)

    def stall_camera(self, i: int, seconds: float) -> None:
        """Fault injection: vehicle i's camera publishes nothing for the next `seconds` wall seconds
        (the sensor hangs; its sequence numbers keep counting, so the gap shows as lost frames)."""
        if not 0 <= seconds <= 3600:
            raise ValueError("a camera stall lasts 0..3600 s")
        self.vehicles[i].camera_stalled_until = time.monotonic() + seconds

    def camera_stalled(self, i: int) -> bool:
        """True while vehicle i's camera is stalled by stall_camera()."""
        return time.monotonic() < self.vehicles[i].camera_stalled_until

    def _capture(self, v: Vehicle) -> None:
        """Take a depth frame now: rendered inline, or queued for the render thread in real-time mode."""
        # Stamped in the FC's time base (camera protocol clock "fc"): it restarts when the FC reboots.
        seq, t_us = v.camera_seq, max(1, int(round((self.time - v.boot_offset) * 1e6)))
        v.camera_seq += 1
        if v.camera_stalled_until and time.monotonic() < v.camera_stalled_until:
            v.frames_withheld += 1
            return
        if self.frame_sink is None and (v.publisher is None or not v.publisher.clients):
            return  # nobody listens: skip the rays, keep the frame counter
        if self._render_thread is None:
            self._deliver(v, seq, t_us, v.camera.render_z16(self.data))
            return
        with self._render_cv:
            # Back-pressure, not drops: the camera always produces its frames; if rendering is the
            # bottleneck the simulated clock runs slower than asked (visible as lag_s, lag_resets).
            while len(self._render_jobs) >= len(self.vehicles) and self._running:
                self._render_cv.wait(0.05)
            self._render_jobs.append((v.index, seq, t_us, self.data.qpos.copy()))
            self._render_cv.notify_all()

    def _deliver(self, v: Vehicle, seq: int, t_us: int, z16: np.ndarray) -> None:
        """Hand a rendered frame to the test sink and the vehicle's socket publisher (thread-safe)."""
        header = v.camera.header(seq, t_us)
        if self.frame_sink is not None:
            self.frame_sink(v.index, header, z16)
        if v.publisher is not None:
            v.publisher.publish(encode_frame(header, z16.tobytes()))

    def _render_loop(self) -> None:
        """Render queued frames on a private MjData (mj_multiRay releases the GIL: runs beside physics)."""
        data = mujoco.MjData(self.model)
        while True:
            with self._render_cv:
                while self._running and not self._render_jobs:
                    self._render_cv.wait(0.1)
                if not self._running:
                    return
                index, seq, t_us, qpos = self._render_jobs.popleft()
                self._render_cv.notify_all()
            data.qpos[:] = qpos
            mujoco.mj_kinematics(self.model, data)
            v = self.vehicles[index]
            self._deliver(v, seq, t_us, v.camera.render_z16(data))

    def _record_all(self) -> None:
        """Append every vehicle's true pose to its trajectory log."""
        for v in self.vehicles:
            q = self.data.qpos[v.qpos_adr : v.qpos_adr + 7]
            v.trajectory.append((self.time, *map(float, q)))

    # ------------------------------------------------------------------ I/O and pacing

    def _fds(self) -> list[int]:
        """Every socket the loop waits on."""
        fds = []
        for v in self.vehicles:
            fds.extend(link.fileno() for link in v.links)
            if v.publisher is not None:
                fds.extend(v.publisher.fileno_list())
        return fds

    def _service_io(self, timeout: float) -> None:
        """Wait up to timeout for socket activity, then serve every endpoint (bounded work)."""
        fds = self._fds()
        if timeout > 0:
            if fds:
                try:
                    select.select(fds, [], [], timeout)
                except (OSError, ValueError):
                    time.sleep(timeout)
            else:
                time.sleep(timeout)
        with self.lock:
            for v in self.vehicles:
                for link in v.links:
                    link.poll(self.time)
                if v.publisher is not None:
                    v.publisher.poll()

    def _run(self) -> None:
        """Thread body: run the loop; an internal error is kept in self.failure for the owner to see."""
        try:
            self._loop()
        except Exception as e:  # a bug in the sim itself: stop stepping, but let the owner know why
            self.failure = e
            self._running = False
            raise

    def _loop(self) -> None:
        """Real-time loop: keep simulated time at wall time x speed, serving I/O while waiting."""
        wall0, sim0 = time.monotonic(), self.time
        self.wall_started = wall0
        while self._running:
            target = sim0 + (time.monotonic() - wall0) * self.speed
            n = 0
            while self.time + PHYSICS_DT <= target and n < MAX_STEPS_PER_BATCH and self._running:
                with self.lock:
                    self._step_once()
                n += 1
            self.lag_s = max(0.0, target - self.time) / self.speed
            if self.lag_s > MAX_LAG_WALL_S:
                # Too far behind to catch up smoothly: forget the debt instead of bursting later.
                wall0, sim0, target = time.monotonic(), self.time, self.time
                self.lag_resets += 1
            wait = (self.time + PHYSICS_DT - target) / self.speed
            self._service_io(min(0.01, max(0.0, wait)))

    def start(self) -> None:
        """Run the simulation in a background thread, paced to real time x speed."""
        if self._thread is not None:
            return
        self._running = True
        if any(v.camera is not None for v in self.vehicles):
            # The render thread spends most time in mj_multiRay without the GIL; a short switch
            # interval lets it get the GIL back quickly for its few numpy calls between rays.
            sys.setswitchinterval(min(sys.getswitchinterval(), 0.001))
            self._render_thread = threading.Thread(
                target=self._render_loop, name="firmware-sim-camera", daemon=True
            )
            self._render_thread.start()
        self._thread = threading.Thread(target=self._run, name="firmware-sim", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """Stop the thread and close every socket."""
        self._running = False
        with self._render_cv:
            self._render_cv.notify_all()
        for th in (self._thread, self._render_thread):
            if th is not None:
                th.join(timeout=5)
        self._thread = self._render_thread = None
        for v in self.vehicles:
            for link in v.links:
                link.close()
            if v.publisher is not None:
                v.publisher.close()

    def __enter__(self) -> Simulation:
        return self

    def __exit__(self, *exc) -> None:
        self.stop()

    # ------------------------------------------------------------------ built-in routes

    def fly_builtin_routes(self) -> None:
        """Arm every vehicle and start its world-provided exploration route as an internal mission."""
        n = len(self.vehicles)
        with self.lock:
            for v in self.vehicles:
                route = self.world.route(v.index, n)
                targets = [NavTarget(0, NAV_TAKEOFF, pos=np.array([0, 0, route[0][2]]))]
                for k, p in enumerate(route[1:], start=1):
                    local = v.odometry.world_to_local_point(p)
                    targets.append(NavTarget(k, NAV_WAYPOINT, pos=local))
                targets.append(NavTarget(len(route), NAV_LAND))
                v.fc.last_state = self.estimated_state(v)
                v.fc.arm(self.time)
                v.fc.load_mission(targets)
                v.fc.start_mission(self.time, 0)

    def route_finished(self, i: int) -> bool:
        """True once vehicle i has completed its mission and is disarmed on the ground."""
        fc = self.vehicles[i].fc
        return fc.mission_index >= len(fc.mission) and not fc.armed


def _px4_link():
    from firmware_sim.mavlink_link import MavlinkLink

    return MavlinkLink


def _ardupilot_link():
    from firmware_sim.ardupilot import ArduCopterLink

    return ArduCopterLink


AUTOPILOTS = {"px4": _px4_link, "ardupilot": _ardupilot_link}
"""Autopilot personalities: name -> the MAVLink instance class (imported when used)."""


def default_params(index: int) -> dict:
    """The small PX4 parameter set the emulator exposes (name -> value)."""
    return {
        "MIS_TAKEOFF_ALT": 2.5,
        "MPC_XY_CRUISE": 2.0,
        "MPC_XY_VEL_MAX": 2.0,
        "MPC_Z_VEL_MAX_UP": 1.0,
        "MPC_LAND_SPEED": 0.7,
        "NAV_ACC_RAD": 0.3,
        "COM_DISARM_PRFLT": 10.0,
        "RTL_RETURN_ALT": 1.5,
        "COM_OF_LOSS_T": 0.5,
        "MAV_SYS_ID": index + 1,
        "SYS_AUTOSTART": 4001,
        "MAV_TYPE": 2,
        "CP_DIST": -1.0,
        "CP_DELAY": 0.4,
        "CP_GO_NO_DATA": 0,
    }


__all__ = ["Simulation", "Vehicle", "default_params", "mat_to_quat", "rot_z"]

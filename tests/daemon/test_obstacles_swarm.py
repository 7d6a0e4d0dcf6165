"""The proof of the shared map reaching the flight controller: drone 1 maps two rooms joined by a door;
drone 2 looks around the first room only, then is commanded at 1 m/s (offboard velocity) through the
door toward the second room's far wall, flying backwards so its own camera never sees that wall. Its
coopd registers drone 1's map onto its own (the daemon's own merging: the FC frames differ by their
origins and a quarter turn) and sends OBSTACLE_DISTANCE from the global map; the emulator's collision
prevention (CP_DIST) stops it at least 0.5 m short of the wall; with collision prevention off it flies
on and the emulator records the contact.

Two coopd daemons in this process against firmware_sim in real time, over MAVLink and the camera
socket on loopback."""

from __future__ import annotations

import math
import threading
import time

import numpy as np
import pytest
from daemon_harness import in_process_memory_mb, run_in_threads, stop_all, wait_until, workdir

from coopd.daemon.config import from_dict
from coopd.daemon.service import Daemon
from coopd.grid.cells import occupied_mask
from firmware_sim.camera import CameraConfig
from firmware_sim.flight import MAIN_OFFBOARD, Setpoint
from firmware_sim.shapes import box_from_corners
from firmware_sim.simulation import Simulation
from firmware_sim.worlds import World
from tests.loopback_fc import free_port

pytestmark = pytest.mark.slow

FAR_WALL_X = 11.0
"""Room B's far wall (its face toward the door), world x."""
ALTITUDE = 1.5
HALF_SPAN = 0.22
"""The airframe's arms reach this far from its centre (Airframe.half_extent)."""


def two_rooms() -> World:
    """Room A (x 0..6) and room B (x 6.2..11) of 8 m width, 2.6 m high, joined by a 2.4 m door at
    y 2.8..5.2 in the wall between them (wide enough to pass keeping CP_DIST from its posts); drone 2
    waits in room A facing the door."""
    h = 2.6
    shapes = [box_from_corners("floor_0", (-0.2, -0.2, -0.1), (11.4, 8.2, 0)),
              box_from_corners("wall_south", (-0.2, -0.2, 0), (11.4, 0, h)),
              box_from_corners("wall_north", (-0.2, 8.0, 0), (11.4, 8.2, h)),
              box_from_corners("wall_west", (-0.2, 0, 0), (0, 8.0, h)),
              box_from_corners("wall_far", (FAR_WALL_X, 0, 0), (FAR_WALL_X + 0.2, 8.0, h)),
              box_from_corners("wall_door_s", (6.0, 0, 0), (6.2, 2.8, h)),
              box_from_corners("wall_door_n", (6.0, 5.2, 0), (6.2, 8.0, h)),
              box_from_corners("wall_lintel", (6.0, 2.8, 2.2), (6.2, 5.2, h)),
              box_from_corners("cabinet_b", (8.5, 6.8, 0), (9.5, 8.0, 1.0)),
              box_from_corners("shelf_a", (2.0, 0.0, 0), (3.0, 0.6, 1.9))]
    loop = np.array([[1.0, 1.5], [5.0, 1.5], [5.0, 6.5], [1.0, 6.5]])
    return World("two_rooms", 0, shapes, np.array([-0.4, -0.4, -0.2]), np.array([11.6, 8.4, 2.8]), loop)


def map_transform_truth(sim: Simulation, daemons: list[Daemon], source: int, target: int) -> np.ndarray:
    """The true 4x4 from vehicle source's map frame to vehicle target's: a map point is the FC's
    reporting-frame point (firmware_sim's frame) less the origin coopd took at its first pose."""

    def world_to_map(i: int) -> np.ndarray:
        odo = sim.vehicle(i).odometry
        a = np.eye(4)
        a[:3, :3] = odo.frame_rot.T
        a[:3, 3] = -odo.frame_rot.T @ odo.origin - np.asarray(daemons[i].link.odometry.origin_enu)
        return a

    return world_to_map(target) @ np.linalg.inv(world_to_map(source))


def displacement_m(estimate, truth, points) -> float:
    """Mean distance between points (N x 3) moved by the estimated and by the true transform."""
    p = np.c_[points, np.ones(len(points))]
    return float(np.linalg.norm((p @ np.asarray(estimate).T - p @ truth.T)[:, :3], axis=1).mean())


def daemon_config(wd, i: int, mav_port: int, share_ports: list[int], camera: str, obstacles: dict):
    return from_dict({
        "vehicle": {"id": i + 1, "mavlink": f"udpin:127.0.0.1:{mav_port + i}"},
        "camera": {"source": f"socket:{camera}"},
        "sharing": {"open": True, "listen_host": "127.0.0.1", "port": share_ports[i],
                    "peers": [f"127.0.0.1:{share_ports[1 - i]}"], "scan_period_s": 0.5},
        "merging": {"enabled": i == 1, "period_s": 2.0, "confirm_before_fusing": False,
                    "distributed": False},
        "obstacles": obstacles,
        "daemon": {"state_dir": str(wd / f"state{i}"), "control_socket": str(wd / f"control{i}.sock"),
                   "memory_mb": in_process_memory_mb(), "checkpoint_period_s": 0.0},
    })


def own_cells_near(daemon: Daemon, sim: Simulation, beyond_x: float) -> int:
    """Occupied cells of the daemon's own map (not its global map) beyond world x = beyond_x, above the
    floor."""
    with daemon.mapper.lock:
        grid = daemon.mapper.grid
        keys = np.argwhere(occupied_mask(grid.cells)) + grid.offset
        points = grid.centres_of(keys)
    odo = sim.vehicle(daemon.config.vehicle.id - 1).odometry
    world = (points + daemon.link.odometry.origin_enu) @ odo.frame_rot.T + odo.origin
    return int(((world[:, 0] > beyond_x) & (world[:, 2] > 0.3)).sum())


class Pilot:
    """Flies one emulated vehicle from a test thread (the simulation runs in its own). Targets are given
    in the world frame and handed to the FC in its own reporting frame (each FC's frame starts at its
    vehicle's start pose, turned with its heading)."""

    def __init__(self, sim: Simulation, i: int):
        self.sim, self.i, self.fc = sim, i, sim.vehicle(i).fc
        self.odometry = sim.vehicle(i).odometry

    def takeoff(self) -> None:
        with self.sim.lock:
            self.fc.last_state = self.sim.estimated_state(self.sim.vehicle(self.i))
            self.fc.arm(self.sim.time)
            self.fc.takeoff(self.sim.time, ALTITUDE)
        wait_until(lambda: self.sim.true_pose(self.i)[0][2] > ALTITUDE - 0.1, 15, 0.1)

    def local_yaw(self, yaw_deg: float) -> float:
        return math.radians(yaw_deg) - self.odometry.frame_yaw

    def goto(self, x: float, y: float, yaw_deg: float, within_s: float = 20.0) -> None:
        """Fly to world (x, y) at the altitude facing yaw_deg (world ENU), and wait until there."""
        target = self.odometry.world_to_local_point([x, y, ALTITUDE])
        with self.sim.lock:
            self.fc.reposition(self.sim.time, target, self.local_yaw(yaw_deg))
        wait_until(lambda: np.linalg.norm(self.sim.true_pose(self.i)[0][:2] - [x, y]) < 0.15, within_s, 0.1)

    def sweep(self, x: float, y: float) -> None:
        """Turn a full circle on the spot, 45 degrees at a time (the camera sees all around)."""
        for yaw in range(0, 361, 45):
            self.goto(x, y, yaw)
            time.sleep(1.0)

    def velocity(self, world_velocity, yaw_deg: float) -> Setpoint:
        """An offboard setpoint: this world velocity, facing yaw_deg (world ENU)."""
        return Setpoint(vel=self.odometry.frame_rot.T @ np.asarray(world_velocity, float),
                        yaw=self.local_yaw(yaw_deg))

    def x(self) -> float:
        return float(self.sim.true_pose(self.i)[0][0])


def test_a_wall_only_a_peer_mapped_stops_the_vehicle_short_of_it():
    wd = workdir("coopd-obstacles-swarm-")
    mav_port = free_port()
    share_ports = [free_port(), free_port()]
    # a depth camera reading to 10 m (as a RealSense does): coopd clears rays beyond its 5 m max range
    # up to 5 m, so a doorway seen from afar is mapped free, not left unknown. Drone 2 starts facing
    # north, so the two FC frames (and maps) differ by a quarter turn as well as by their origins.
    sim = Simulation(two_rooms(), 2, seed=0, noise="none", mavlink_base_port=mav_port,
                     start_poses=[(1.0, 6.5, 0.0, 0.0), (1.0, 4.0, 0.0, math.pi / 2)],
                     camera_dir=str(wd / "cam"), camera=CameraConfig(max_m=10.0))
    daemons: list[Daemon] = []
    runners = []
    try:
        # the default [obstacles] (when_fc_asks): drone 2's FC has collision prevention on, drone 1's not
        obstacles = [{}, {"rate_hz": 10.0, "max_distance_m": 3.0}]
        sim.vehicle(1).fc.params["CP_DIST"] = 1.0
        for i in range(2):
            daemons.append(Daemon(daemon_config(wd, i, mav_port, share_ports, sim.vehicle(i).camera_path,
                                                obstacles[i])))
        runners = run_in_threads(daemons)
        sim.start()
        mapper, dasher = Pilot(sim, 0), Pilot(sim, 1)
        # drone 2 looks around room A from where it took off (so it has a map to register drone 1's
        # onto), while drone 1 maps room A, goes through the door and maps room B, then lands out of
        # the way. Drone 1 looks all around from two points per room, each in view of the other: the
        # cells within the camera's minimum range of one are seen from the other.
        def look_around_room_a():
            dasher.takeoff()
            dasher.sweep(1.0, 4.0)

        looking = threading.Thread(target=look_around_room_a, daemon=True)
        looking.start()
        mapper.takeoff()
        for x, y in ((3.0, 5.8), (3.0, 2.2), (5.0, 4.0), (7.5, 4.0), (8.5, 5.8), (8.5, 2.2)):
            here = sim.true_pose(0)[0]
            mapper.goto(x, y, math.degrees(math.atan2(y - here[1], x - here[0])))  # looking ahead
            if (x, y) not in ((5.0, 4.0), (7.5, 4.0)):  # the door is passed, not looked around from
                mapper.sweep(x, y)
        mapper.goto(7.0, 7.2, 90.0)
        with sim.lock:
            mapper.fc.land(sim.time)
        looking.join(60)
        assert daemons[0].frames_mapped > 50, daemons[0].handle_status({})["mapping"]
        # drone 2's coopd registers drone 1's map onto its own (the daemon's own merging) and places it
        truth = map_transform_truth(sim, daemons, source=0, target=1)
        far_wall = np.array([[FAR_WALL_X, y, z] for y in (1.0, 4.0, 7.0) for z in (0.5, 2.0)])
        odo1 = sim.vehicle(0).odometry
        far_wall_in_map1 = (far_wall - odo1.origin) @ odo1.frame_rot - daemons[0].link.odometry.origin_enu
        merged = wait_until(lambda: daemons[1].merger.offsets.get(1, {}).get("accepted"), 60, 0.5)
        fit = daemons[1].merger.offsets.get(1, {})
        assert merged, daemons[1].handle_status({})["merges"]
        wall_error = displacement_m(np.reshape(fit["transform"], (4, 4)), truth, far_wall_in_map1)
        assert wall_error <= 0.15, (wall_error, fit, truth.round(3).tolist())
        # drone 2 never saw room B: nothing of its own map is near the far wall
        own_near_wall = own_cells_near(daemons[1], sim, FAR_WALL_X - 3.0)
        assert own_near_wall == 0, own_near_wall  # nothing of room B but its floor (seen from afar)
        # drone 2: 1 m/s toward the far wall through the door, flying backwards (facing west), so its
        # camera never sees room B: only drone 1's map shows the wall
        assert not daemons[0].handle_status({})["obstacles"]["sending"]  # its FC does not use them
        dasher.goto(1.0, 4.0, 180.0)
        backwards = dasher.velocity([1.0, 0.0, 0.0], 180.0)
        with sim.lock:
            dasher.fc.set_offboard_setpoint(backwards)
            assert dasher.fc.set_mode(MAIN_OFFBOARD, 0, sim.time) == 0
        closest, t_end = math.inf, time.monotonic() + 25.0
        while time.monotonic() < t_end:
            with sim.lock:
                dasher.fc.set_offboard_setpoint(backwards)
            closest = min(closest, FAR_WALL_X - dasher.x())
            time.sleep(0.1)
        status = daemons[1].handle_status({})["obstacles"]
        g = daemons[1].merger.global_map()[0]
        report = {"global": (g.counts(), [b.round(2).tolist() for b in g.bounds_m()]),
                  "wall_error_m": round(wall_error, 3), "fit": {k: fit[k] for k in ("score", "yaw_deg")},
                  "closest_m": round(closest, 3), "pose": sim.true_pose(1)[0].round(2).tolist(),
                  "last": daemons[1].obstacles.last.tolist(), "obstacles": status,
                  "contacts": sim.contacts(1), "cut_steps": dasher.fc.cp_cut_steps}
        assert dasher.x() > 7.0, report  # through the door into the room it never saw
        assert closest - HALF_SPAN >= 0.5, report
        assert sim.vehicle(1).contact_count == 0, report
        assert status["nearest_m"] is not None and status["nearest_m"] <= 1.6, report
        assert status["sending"] and not status["enabled"] and status["fc"] == "CP_DIST = 1 m", report
        # its camera looked back the whole way: it saw room B's floor, never the far wall
        assert own_cells_near(daemons[1], sim, FAR_WALL_X - 1.0) == 0, report
        # collision prevention off: the same command flies it into the wall, and the contact is recorded
        with sim.lock:
            dasher.fc.params["CP_DIST"] = -1.0
        t_end = time.monotonic() + 15.0
        while time.monotonic() < t_end and sim.vehicle(1).contact_count == 0:
            with sim.lock:
                dasher.fc.set_offboard_setpoint(backwards)
            time.sleep(0.1)
        contacts = sim.contacts(1)
        assert contacts and contacts[0].geom == "wall_far", contacts
        print({**report, "contact_without_cp": contacts[0]})
    finally:
        stop_all(sim, daemons, runners, wd)

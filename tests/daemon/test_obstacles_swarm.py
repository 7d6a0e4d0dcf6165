"""The proof of the shared map reaching the flight controller: drone 1 maps a room; drone 2, which has
never seen it (no camera), is commanded at 1 m/s (offboard velocity) through a door it never mapped
toward the room's far wall. Its coopd sends OBSTACLE_DISTANCE from the global map (drone 1's map,
received over MTP and merged), the emulator's collision prevention (CP_DIST) stops it at least 0.5 m
short of the wall; with collision prevention off it flies on and the emulator records the contact.

Two coopd daemons in this process against firmware_sim in real time, over MAVLink and the camera
socket on loopback. Registration is not what is tested here (tests/merging does): drone 2's merge
function places drone 1's map by the simulator's true offset between their map frames
(merge_with_true_offset), then fuses it exactly as merging does (fuse_transformed)."""

from __future__ import annotations

import math
import shutil
import threading
import time

import numpy as np
import pytest
from daemon_harness import in_process_memory_mb, wait_until, workdir

from coopd.daemon.config import from_dict
from coopd.daemon.service import Daemon
from coopd.grid import OCCUPIED_THRESHOLD, fuse_transformed
from coopd.merging.multi import GlobalMergeResult
from coopd.merging.pair import MergeResult
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


def merge_with_true_offset(daemons: list[Daemon]):
    """A merge function for drone 2's daemon that places each received map by the simulator's truth:
    both vehicles report the world frame (frame="world", no noise), so the map frames differ by their
    origins only; fused exactly as merging fuses (fuse_transformed)."""

    def merge(reference, others, params=None, **_):
        merged = reference.copy()
        results = []
        started = len(daemons) == 2  # the daemon's own warm-up merges before the list is complete
        for grid in others:
            t = np.eye(4)
            if started:
                theirs, mine = (np.asarray(d.link.odometry.origin_enu) for d in daemons)
                t[:3, 3] = theirs - mine
            fuse_transformed(merged, grid, t, OCCUPIED_THRESHOLD)
            results.append(MergeResult(True, t, 0, 1.0, 0, 0, 0.0, "accepted"))
        return GlobalMergeResult(merged, results, 1)

    return merge


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


class Pilot:
    """Flies one emulated vehicle from the test thread (the simulation runs in its own)."""

    def __init__(self, sim: Simulation, i: int):
        self.sim, self.i, self.fc = sim, i, sim.vehicle(i).fc

    def takeoff(self) -> None:
        with self.sim.lock:
            self.fc.last_state = self.sim.estimated_state(self.sim.vehicle(self.i))
            self.fc.arm(self.sim.time)
            self.fc.takeoff(self.sim.time, ALTITUDE)

    def goto(self, x: float, y: float, yaw_deg: float, within_s: float = 20.0) -> None:
        """Fly to (x, y) at the altitude facing yaw_deg (ENU), and wait until there."""
        with self.sim.lock:
            self.fc.reposition(self.sim.time, np.array([x, y, ALTITUDE]), math.radians(yaw_deg))
        wait_until(lambda: np.linalg.norm(self.sim.true_pose(self.i)[0][:2] - [x, y]) < 0.15, within_s, 0.1)

    def sweep(self, x: float, y: float) -> None:
        """Turn a full circle on the spot, 45 degrees at a time (the camera sees all around)."""
        for yaw in range(0, 361, 45):
            self.goto(x, y, yaw)
            time.sleep(1.0)

    def x(self) -> float:
        return float(self.sim.true_pose(self.i)[0][0])


def test_a_wall_only_a_peer_mapped_stops_the_vehicle_short_of_it():
    wd = workdir("coopd-obstacles-swarm-")
    mav_port = free_port()
    share_ports = [free_port(), free_port()]
    # a depth camera reading to 10 m (as a RealSense does): coopd clears rays beyond its 5 m max range
    # up to 5 m, so a doorway seen from afar is mapped free, not left unknown
    sim = Simulation(two_rooms(), 2, seed=0, noise="none", frame="world", mavlink_base_port=mav_port,
                     start_poses=[(1.0, 6.5, 0.0, 0.0), (1.0, 4.0, 0.0, 0.0)], camera_dir=str(wd / "cam"),
                     camera=CameraConfig(max_m=10.0))
    daemons: list[Daemon] = []
    runners = []
    try:
        cameras = [sim.vehicle(0).camera_path, str(wd / "cam" / "none.sock")]  # drone 2: no camera
        obstacles = [{}, {"enabled": True, "rate_hz": 10.0, "max_distance_m": 3.0}]
        for i in range(2):
            merge_fn = merge_with_true_offset(daemons) if i == 1 else None
            daemons.append(Daemon(daemon_config(wd, i, mav_port, share_ports, cameras[i], obstacles[i]),
                                  merge_fn=merge_fn))
        for d in daemons:
            d.start()
            runners.append(threading.Thread(target=d.run, daemon=True))
            runners[-1].start()
        sim.start()
        mapper, dasher = Pilot(sim, 0), Pilot(sim, 1)
        # drone 1 maps room A, goes through the door and maps room B, then lands out of the way. It
        # looks all around from two points per room, each in view of the other: the cells within the
        # camera's minimum range of one are seen from the other.
        mapper.takeoff()
        for x, y in ((3.0, 5.8), (3.0, 2.2), (5.0, 4.0), (7.5, 4.0), (8.5, 5.8), (8.5, 2.2)):
            here = sim.true_pose(0)[0]
            mapper.goto(x, y, math.degrees(math.atan2(y - here[1], x - here[0])))  # looking ahead
            if (x, y) not in ((5.0, 4.0), (7.5, 4.0)):  # the door is passed, not looked around from
                mapper.sweep(x, y)
        mapper.goto(7.0, 7.2, 90.0)
        with sim.lock:
            mapper.fc.land(sim.time)
        frames = daemons[0].frames_mapped
        assert frames > 50, daemons[0].handle_status({})["mapping"]
        # drone 2's coopd receives that map and merges it into its global map
        merged = wait_until(lambda: daemons[1].merger.global_map() is not None
                            and daemons[1].merger.offsets.get(1, {}).get("accepted"), 30, 0.5)
        assert merged, daemons[1].handle_status({})["merges"]
        assert daemons[1].mapper.grid.counts().known == 0  # drone 2 itself never mapped anything
        # drone 2: collision prevention on, take off, then 1 m/s toward the far wall through the door
        with sim.lock:
            dasher.fc.params["CP_DIST"] = 1.0
        dasher.takeoff()
        wait_until(lambda: sim.true_pose(1)[0][2] > ALTITUDE - 0.1, 15, 0.1)
        forward = Setpoint(vel=np.array([1.0, 0.0, 0.0]), yaw=0.0)
        with sim.lock:
            dasher.fc.set_offboard_setpoint(forward)
            assert dasher.fc.set_mode(MAIN_OFFBOARD, 0, sim.time) == 0
        closest, t_end = math.inf, time.monotonic() + 25.0
        while time.monotonic() < t_end:
            with sim.lock:
                dasher.fc.set_offboard_setpoint(forward)
            closest = min(closest, FAR_WALL_X - dasher.x())
            time.sleep(0.1)
        status = daemons[1].handle_status({})["obstacles"]
        g = daemons[1].merger.global_map()[0]
        report = {"global": (g.counts(), [b.round(2).tolist() for b in g.bounds_m()]),
                  "map_pose": daemons[1].link.poses.latest().position.round(2).tolist(),
                  "origins": [d.link.odometry.origin_enu.round(2).tolist() for d in daemons],
                  "closest_m": round(closest, 3), "pose": sim.true_pose(1)[0].round(2).tolist(),
                  "last": daemons[1].obstacles.last.tolist(), "obstacles": status,
                  "contacts": sim.contacts(1), "cut_steps": dasher.fc.cp_cut_steps}
        assert dasher.x() > 7.0, report  # through the door into the room it never saw
        assert closest - HALF_SPAN >= 0.5, report
        assert sim.vehicle(1).contact_count == 0, report
        assert status["nearest_m"] is not None and status["nearest_m"] <= 1.6, report
        # collision prevention off: the same command flies it into the wall, and the contact is recorded
        with sim.lock:
            dasher.fc.params["CP_DIST"] = -1.0
        t_end = time.monotonic() + 15.0
        while time.monotonic() < t_end and sim.vehicle(1).contact_count == 0:
            with sim.lock:
                dasher.fc.set_offboard_setpoint(forward)
            time.sleep(0.1)
        contacts = sim.contacts(1)
        assert contacts and contacts[0].geom == "wall_far", contacts
        print({**report, "contact_without_cp": contacts[0]})
    finally:
        sim.stop()
        for d, r in zip(daemons, runners, strict=False):
            d.request_stop("test")
            r.join(5)
            d.shutdown()
        shutil.rmtree(wd, ignore_errors=True)

"""Real flight maps: firmware_sim drones fly their built-in routes and map with their drifting odometry.

Each drone's depth frames go through coopd's Mapper at the pose its estimator reports (noise-free
drifting estimate plus the emulator's white noise), expressed in the drone's map frame: its
reporting frame translated so the first reported pose is the origin, as the daemon does
(coopd/vehicle/odometry.py). The truth recorded per map is that map frame in the world at t = 0,
so whatever drift bent into the map is what merging has to live with. Maps are cached as .npz.
"""

import hashlib
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

from coopd.geometry import invert, matrix_to_quat, rigid
from coopd.grid import OccupancyGrid
from coopd.mapping import CameraMount, Intrinsics, Mapper, MapperConfig, Pose, raycast

WORLDS = ("maze", "small_house", "small_warehouse", "bookstore", "hospital", "racetrack")
CACHE_DIR = Path("out/simset")


@dataclass(frozen=True)
class FlightMap:
    """One drone's local map of one flight and where its map frame sits in the world."""

    world: str
    seed: int
    vehicle: int
    grid: OccupancyGrid
    map_in_world: np.ndarray
    """4x4: map-frame points to world points (the frame at t = 0, before any drift)."""
    frames: int
    flight_s: float
    route_finished: bool


def truth_b_to_a(a: FlightMap, b: FlightMap) -> np.ndarray:
    """The transform carrying b's map frame into a's (what merge_pair should return)."""
    return invert(a.map_in_world) @ b.map_in_world


def true_pose_at(sim, index: int, t: float) -> tuple[np.ndarray, np.ndarray]:
    """World position and rotation of a body at time t, interpolated in its logged true trajectory."""
    from firmware_sim.frames import quat_to_mat

    traj = sim.trajectory(index)
    k = int(np.clip(np.searchsorted(traj[:, 0], t), 1, len(traj) - 1))
    t0, t1 = traj[k - 1, 0], traj[k, 0]
    w = float(np.clip((t - t0) / max(t1 - t0, 1e-9), 0.0, 1.0))
    q0, q1 = traj[k - 1, 4:8], traj[k, 4:8] * np.sign(np.dot(traj[k - 1, 4:8], traj[k, 4:8]) or 1.0)
    q = (1 - w) * q0 + w * q1
    return (1 - w) * traj[k - 1, 1:4] + w * traj[k, 1:4], quat_to_mat(q / np.linalg.norm(q))


def reported_pose(sim, index: int, noisy: bool, delay_s: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """(position, rotation) of the body in the reporting frame: the pose the camera renders at, or
    the estimate delay_s earlier (a frame stamped late against the odometry)."""
    v = sim.vehicle(index)
    if delay_s > 0:
        pos_w, rot_w = true_pose_at(sim, index, sim.time - delay_s)
    else:
        pos_w = sim.data.xpos[v.body_id].copy()
        rot_w = sim.data.xmat[v.body_id].reshape(3, 3).copy()
    p, r, vel = v.odometry.estimate(sim.time - delay_s, pos_w, rot_w, np.zeros(3))
    if noisy:
        p, r, _ = v.odometry.noisy(p, r, vel)
    return p, r


def start_lap_missions(sim, laps: int) -> None:
    """Arm every drone and fly its built-in route `laps` times over (fly_builtin_routes, repeated)."""
    from firmware_sim.flight import NAV_LAND, NAV_TAKEOFF, NAV_WAYPOINT, NavTarget

    n = len(sim.vehicles)
    with sim.lock:
        for v in sim.vehicles:
            route = sim.world.route(v.index, n)
            points = [v.odometry.world_to_local_point(p) for p in route[1:]] * laps
            targets = [NavTarget(0, NAV_TAKEOFF, pos=np.array([0, 0, route[0][2]]))]
            targets += [NavTarget(k, NAV_WAYPOINT, pos=p) for k, p in enumerate(points, start=1)]
            targets.append(NavTarget(len(points) + 1, NAV_LAND))
            v.fc.last_state = sim.estimated_state(v)
            v.fc.arm(sim.time)
            v.fc.load_mission(targets)
            v.fc.start_mission(sim.time, 0)


def camera(rate_hz: float | None = None):
    """The emulator's depth camera, at rate_hz frames per second (None: its default rate)."""
    from firmware_sim.camera import CameraConfig

    cfg = CameraConfig() if rate_hz is None else replace(CameraConfig(), rate_hz=float(rate_hz))
    cfg.validate()
    return cfg


def fly(world_name: str, seed: int, n_vehicles: int = 3, laps: int = 1, ground_s: float = 0.0,
        pose_delay_s: float = 0.0, max_flight_s: float = 900.0, noisy_poses: bool = True,
        config: MapperConfig | None = None, each_second=None,
        camera_rate_hz: float | None = None) -> list[FlightMap]:
    """Fly every drone's built-in route `laps` times in-process and return each drone's local map.

    ground_s: seconds the drones sit on the ground, mapping and drifting, before they take off (as
    when the daemons start well before the mission). pose_delay_s: each frame is mapped at the pose
    of that much earlier (camera and odometry clocks out of step). each_second(sim_time, mappers), if
    given, is called after every simulated second of flight (e.g. to record the maps as they grow).
    camera_rate_hz: every camera's frame rate (None: the emulator's default); fewer frames make a
    flight of many drones cheaper to fly, and each map a little sparser."""
    from firmware_sim.simulation import Simulation
    from firmware_sim.worlds import build_world

    sim = Simulation(build_world(world_name, seed), n_vehicles, seed=seed, mavlink=False,
                     camera=camera(camera_rate_hz))
    origins = [reported_pose(sim, i, noisy_poses)[0] for i in range(n_vehicles)]
    mappers = [Mapper(config or MapperConfig()) for _ in range(n_vehicles)]
    mount = CameraMount()

    def sink(i, header, z16):
        if sim.time > ground_s and sim.route_finished(i):
            return
        p, r = reported_pose(sim, i, noisy_poses, pose_delay_s)
        intr = Intrinsics(header["w"], header["h"], header["fx"], header["fy"], header["cx"], header["cy"],
                          header["scale"])
        body = Pose(p - origins[i], matrix_to_quat(r))
        mappers[i].integrate(z16, intr, mount.camera_pose(body), header["t_us"] * 1e-6)

    sim.frame_sink = sink
    if ground_s > 0:
        sim.step(ground_s)
    start_lap_missions(sim, laps)
    while sim.time < max_flight_s + ground_s and not all(sim.route_finished(i) for i in range(n_vehicles)):
        sim.step(1.0)
        if each_second is not None:
            each_second(sim.time, mappers)
    out = []
    for i, m in enumerate(mappers):
        odo = sim.vehicle(i).odometry
        frame = rigid(odo.frame_rot, odo.origin) @ rigid(translation=origins[i])
        out.append(FlightMap(world_name, seed, i, m.grid.shrunk(), frame, m.totals.frames, sim.time,
                             sim.route_finished(i)))
    return out


def mapper_tag(config: MapperConfig | None = None) -> str:
    """A short digest of the mapper settings (thread count aside: any count maps alike) and of its ray
    casting code: flights mapped before the mapper changed are cached under another name, never read
    as today's."""
    settings = {k: v for k, v in asdict(config or MapperConfig()).items() if k != "threads"}
    code = Path(raycast.__file__).read_bytes()
    return hashlib.sha256(repr(sorted(settings.items())).encode() + code).hexdigest()[:8]


def cache_path(world_name: str, seed: int, n_vehicles: int, laps: int, ground_s: float, pose_delay_s: float,
               cache_dir: Path = CACHE_DIR, camera_rate_hz: float | None = None,
               mapper: MapperConfig | None = None) -> Path:
    """Where flight_maps keeps one flight's maps (a camera rate other than the default is in the name,
    and the mapper's settings, mapper_tag, always are)."""
    rate = camera(camera_rate_hz).rate_hz
    suffix = ("" if laps == 1 else f"_l{laps}") + ("" if ground_s == 0 else f"_g{ground_s:g}") + \
        ("" if pose_delay_s == 0 else f"_d{pose_delay_s:g}") + \
        ("" if rate == camera().rate_hz else f"_c{rate:g}")
    return Path(cache_dir) / f"{world_name}_s{seed}_n{n_vehicles}{suffix}_m{mapper_tag(mapper)}.npz"


def save(maps: list[FlightMap], path: Path) -> None:
    """Write one flight's maps to an .npz."""
    path.parent.mkdir(parents=True, exist_ok=True)
    arrays = {}
    for m in maps:
        k = f"v{m.vehicle}_"
        arrays |= {k + "cells": m.grid.cells, k + "offset": m.grid.offset, k + "map_in_world": m.map_in_world,
                   k + "meta": np.array([m.grid.resolution, m.frames, m.flight_s, float(m.route_finished)])}
    tmp = path.with_suffix(".tmp.npz")
    np.savez_compressed(tmp, **arrays)
    tmp.replace(path)


def load(path: Path, world_name: str, seed: int) -> list[FlightMap]:
    """Read maps written by save()."""
    with np.load(path) as z:
        n = len([k for k in z.files if k.endswith("_cells")])
        out = []
        for i in range(n):
            k = f"v{i}_"
            res, frames, flight_s, finished = z[k + "meta"]
            grid = OccupancyGrid(z[k + "cells"].copy(), float(res), z[k + "offset"].copy())
            out.append(FlightMap(world_name, seed, i, grid, z[k + "map_in_world"].copy(), int(frames),
                                 float(flight_s), bool(finished)))
    return out


def flight_maps(world_name: str, seed: int, n_vehicles: int = 3, laps: int = 1, ground_s: float = 0.0,
                pose_delay_s: float = 0.0, cache_dir: Path = CACHE_DIR,
                camera_rate_hz: float | None = None, mapper: MapperConfig | None = None) -> list[FlightMap]:
    """Cached fly(): the maps of one world and seed, flown once and read back afterwards (mapper: the
    drones' mapper settings, defaults when None)."""
    path = cache_path(world_name, seed, n_vehicles, laps, ground_s, pose_delay_s, cache_dir, camera_rate_hz,
                      mapper)
    if path.exists():
        return load(path, world_name, seed)
    maps = fly(world_name, seed, n_vehicles, laps, ground_s, pose_delay_s, config=mapper,
               camera_rate_hz=camera_rate_hz)
    save(maps, path)
    return maps


def known_overlap(a: OccupancyGrid, b: OccupancyGrid, t_ab: np.ndarray, max_points: int = 200_000) -> float:
    """Share of the smaller map's known cells that the other map also knows, under t_ab (b -> a)."""
    def known_points(g):
        pts = (np.argwhere(g.cells >= 0) + g.offset) * g.resolution
        return pts[:: max(1, len(pts) // max_points)], len(pts)

    def hits(points, t, grid):
        moved = points @ t[:3, :3].T + t[:3, 3]
        return float(np.mean(grid.values_at(moved) >= 0)) if len(points) else 0.0

    pa, na = known_points(a)
    pb, nb = known_points(b)
    return hits(pb, t_ab, a) if nb <= na else hits(pa, invert(t_ab), b)

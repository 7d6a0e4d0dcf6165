"""Accuracy against ground truth in every world: runs scripts/demo (3 drones, default noise) once per
world, one after another, then scores every drone's own and global map against the world's analytic
surfaces, and replays the same camera frames and poses into coopd's mapper and into OctoMap in the
same run. Writes out/bench/accuracy.json and a markdown table (out/bench/accuracy.md).

Surface metric (firmware_sim/accuracy.py): precision = share of occupied cell centres within one
cell of the true surface (mean and p95 distance too); recall = share of the surface points the
drone's camera saw (truth ray casts from its true poses, within max range) with an occupied cell
within one cell. The strict voxel figures of the demo stay as a secondary column.

Replay: the drone's true trajectory, its camera re-rendered (MuJoCo ray casts against the world,
readings up to CAMERA_REACH_M as a real depth camera reports them), every --frame-step-th frame, true
poses, into coopd (beyond_max_range "clear" and "drop") and OctoMap (insertPointCloud, same
resolution, maxrange = max range); free = share of truly free points along the rays (more than a
cell from any surface, within max range) that the map holds free.

Goal: every drone, own and global map: surface precision and recall >= 0.95; global no worse than
the lowest of its members' own maps by more than 0.02; coopd >= OctoMap on both (replay).
Usage: scripts/benchmarks/accuracy.py [--worlds a,b] [--drones 3] [--seed 1] [--speed 2] [--frame-step 3]
       [--autopilot px4|ardupilot] [--network auto|netns|loopback] [--port-base N] [--tabulate]
       [--no-replay] [--depth-noise SIGMA] [--mapper KEY=VALUE,...]
(--tabulate: no flights, score and tabulate the runs already in out/bench/accuracy/WORLD/)
--depth-noise gives the replayed frames the emulated camera's range noise (SIGMA * depth^2, seeded; the
truth samples stay those of the clean frames) in both mappers, --mapper changes the coopd replay's
settings (e.g. miss_decrement=5); either names the outputs after it (out/bench/accuracy-noise0.01.json,
accuracy-miss_decrement5.json) but the flights are the run's own (out/bench/accuracy/WORLD/, or
accuracy-ardupilot/WORLD/): use them with --tabulate, since a flight would replace the one the other
tables were scored on.
--autopilot ardupilot flies ArduCopter-personality drones (coopd builds its poses from
LOCAL_POSITION_NED + ATTITUDE_QUATERNION) and writes out/bench/accuracy-ardupilot.{json,md} and
out/bench/accuracy-ardupilot/WORLD/, beside the PX4 run's files.
"""

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")   # OctoMap's insertPointCloud: one thread, as coopd's mapper

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "scripts" / "benchmarks"))

from _overrides import overrides  # noqa: E402

from coopd.geometry import matrix_to_quat, quat_to_matrix  # noqa: E402
from coopd.io import load_cmap  # noqa: E402
from coopd.mapping import Intrinsics, Mapper, MapperConfig, Pose  # noqa: E402
from firmware_sim import accuracy as acc  # noqa: E402
from firmware_sim.camera import CameraConfig, body_from_camera, optical_rays  # noqa: E402
from firmware_sim.worlds import GENERATORS, build_world  # noqa: E402

GOAL = {"surface_precision": 0.95, "surface_recall": 0.95, "global_vs_members": 0.02}
CAMERA_REACH_M = 10.0
"""Farthest depth the replayed camera reports (a RealSense D435's reach); beyond it, no return."""
FRAME_STEP = 3
"""Replay every FRAME_STEP-th camera frame by default (--frame-step): OctoMap takes 0.1-0.2 s a frame."""
SAMPLE_PIXEL_STEP = 8
"""Truth samples: every SAMPLE_PIXEL_STEP-th pixel along both image axes of every replayed frame."""
FREE_RAYS = 6000
"""Rays (drawn from the sampled ones, seeded) whose free points are scored per drone."""


# ------------------------------------------------------------------------------- the flights
def run_demo(world: str, a, run_out: Path) -> dict | None:
    """One demo run (none with --tabulate); its report, or None without one."""
    report_path = run_out / "demo_report.json"
    if not a.tabulate:
        report_path.unlink(missing_ok=True)
        cmd = [sys.executable, str(ROOT / "scripts" / "demo.py"), "--world", world, "--drones", str(a.drones),
               "--seed", str(a.seed), "--speed", str(a.speed), "--timeout", str(a.demo_timeout),
               "--out", str(run_out), "--autopilot", a.autopilot, "--network", a.network]
        if a.port_base is not None:
            cmd += ["--port-base", str(a.port_base)]
        with open(run_out / "demo.log", "wb") as log:
            rc = subprocess.call(cmd, stdout=log, stderr=subprocess.STDOUT, cwd=ROOT)
        if not report_path.exists():
            print(f"accuracy: {world}: demo exited {rc} without a report; see {run_out / 'demo.log'}")
            return None
    return json.loads(report_path.read_text()) if report_path.exists() else None


def load_flight(path: Path) -> dict:
    """A drone's flight_<id>.npz (scripts/demo): trajectory, camera, map frame, global map members."""
    with np.load(path) as f:
        c = f["camera"]
        cam = CameraConfig(width=int(c[0]), height=int(c[1]), hfov_deg=float(c[2]), rate_hz=float(c[3]),
                           tilt_down_deg=float(c[4]), offset_body=tuple(float(v) for v in c[5:8]))
        return {"trajectory": f["trajectory"], "camera": cam, "world_from_map": f["world_from_map"],
                "members": [int(v) for v in f["members"]]}


# ------------------------------------------------------------------------------- the replay
def flight_span(trajectory: np.ndarray, pad_s: float = 1.0) -> np.ndarray:
    """The rows of a trajectory from pad_s before the vehicle first moved (5 cm) to pad_s after it
    last moved: the time on the ground sees what takeoff sees, and costs the replay nothing new."""
    left_start = np.linalg.norm(trajectory[:, 1:4] - trajectory[0, 1:4], axis=1) > 0.05
    before_end = np.linalg.norm(trajectory[:, 1:4] - trajectory[-1, 1:4], axis=1) > 0.05
    if not left_start.any():
        return trajectory
    t = trajectory[:, 0]
    t0, t1 = t[np.argmax(left_start)] - pad_s, t[len(t) - 1 - np.argmax(before_end[::-1])] + pad_s
    return trajectory[(t >= t0) & (t <= t1)]


def camera_poses(trajectory: np.ndarray, cam: CameraConfig, period_s: float):
    """(origin, optical-frame rotation) in the world every period_s along a true trajectory (rows t,
    x, y, z, qw, qx, qy, qz), interpolated between its samples."""
    t = trajectory[:, 0]
    out = []
    for tf in np.arange(t[0], t[-1], period_s):
        k = min(int(np.searchsorted(t, tf, side="right")) - 1, len(t) - 2)
        w = (tf - t[k]) / max(t[k + 1] - t[k], 1e-9)
        pos = (1 - w) * trajectory[k, 1:4] + w * trajectory[k + 1, 1:4]
        q0, q1 = trajectory[k, 4:8], trajectory[k + 1, 4:8]
        q = (1 - w) * q0 + w * (q1 if np.dot(q0, q1) >= 0 else -q1)
        r_body = quat_to_matrix(q / np.linalg.norm(q))
        out.append((pos + r_body @ np.asarray(cam.offset_body), r_body @ body_from_camera(cam)))
    return out


def render_frames(world, cam: CameraConfig, poses):
    """Depth images (metres, NaN = no return within CAMERA_REACH_M) of the world alone, by MuJoCo
    ray casts from each (origin, rotation)."""
    import mujoco

    model = mujoco.MjModel.from_xml_string(world.mjcf)
    data = mujoco.MjData(model)
    mujoco.mj_kinematics(model, data)
    rays = optical_rays(cam)
    n = len(rays)
    geomid, dist = np.zeros(n, np.int32), np.zeros(n, np.float64)
    cutoff = CAMERA_REACH_M * float(np.max(np.linalg.norm(rays, axis=1))) + 0.01
    frames = []
    for origin, rot in poses:
        mujoco.mj_multiRay(model, data, origin, (rays @ rot.T).reshape(-1), None, 1, -1, geomid, dist,
                           None, n, cutoff)
        depth = np.where((dist >= 0) & (dist <= CAMERA_REACH_M), dist, np.nan)
        frames.append(depth.reshape(cam.height, cam.width).astype(np.float32))
    return frames


def replay_coopd(frames, poses, cam: CameraConfig, beyond: str, settings: dict | None = None):
    """coopd's mapper (defaults, as the daemons, unless settings change some) fed the frames at their
    true poses."""
    fx, fy, cx, cy = cam.intrinsics()
    intr = Intrinsics(cam.width, cam.height, fx, fy, cx, cy)
    mapper = Mapper(MapperConfig(**(settings or {}) | {"beyond_max_range": beyond}))
    for depth, (origin, rot) in zip(frames, poses, strict=True):
        mapper.integrate(depth, intr, Pose(origin, matrix_to_quat(rot)))
    return mapper.grid


def replay_octomap(frames, poses, cam: CameraConfig, config: MapperConfig):
    """OctoMap (insertPointCloud, its default sensor model, maxrange = max range) fed the same
    frames at the same poses, as a grid (occupied 100, free 0, unknown -1) and its frame in the
    world (OctoMap's cells are centred at (k + 0.5) * resolution, coopd's at k * resolution)."""
    import octomap

    rays = optical_rays(cam)
    tree = octomap.OcTree(config.resolution)
    for depth, (origin, rot) in zip(frames, poses, strict=True):
        d = depth.reshape(-1).astype(np.float64)
        ok = np.isfinite(d) & (d >= config.min_range)
        tree.insertPointCloud(origin + (rays[ok] * d[ok, None]) @ rot.T, origin, maxrange=config.max_range)
    return octree_grid(tree, config.resolution)


def octree_grid(tree, res: float):
    """A dense grid of an OcTree's leaves (larger, pruned leaves fill all their cells)."""
    import types

    centres, sizes, occupied = [], [], []
    for leaf in tree.begin_leafs():
        centres.append(leaf.getCoordinate())
        sizes.append(leaf.getSize())
        occupied.append(tree.isNodeOccupied(leaf))
    centres, sizes, occupied = np.array(centres), np.array(sizes), np.array(occupied, bool)
    span = np.round(sizes / res).astype(np.int64)
    first = np.round((centres - sizes[:, None] / 2) / res).astype(np.int64)
    lo, hi = first.min(axis=0), (first + span[:, None]).max(axis=0)
    cells = np.full(hi - lo, -1, np.int8)
    for n in np.unique(span):
        pick = span == n
        block = np.stack(np.meshgrid(*[np.arange(n)] * 3, indexing="ij"), axis=-1).reshape(-1, 3)
        for value, which in ((0, pick & ~occupied), (100, pick & occupied)):
            keys = (first[which][:, None, :] + block[None]).reshape(-1, 3) - lo
            cells[tuple(keys.T)] = value
    world_from_map = np.eye(4)
    world_from_map[:3, 3] = res / 2
    return types.SimpleNamespace(cells=cells, offset=lo, resolution=res), world_from_map


def truth_samples(frames, poses, cam: CameraConfig, shapes, max_range: float, res: float, seed: int):
    """Surface points the frames saw within max range, and truly free points along a seeded subset
    of the same rays that have a reading (firmware_sim.accuracy.ray_samples)."""
    rays = optical_rays(cam).reshape(cam.height, cam.width, 3)[::SAMPLE_PIXEL_STEP, ::SAMPLE_PIXEL_STEP]
    rays = rays.reshape(-1, 3)
    norms = np.linalg.norm(rays, axis=1)
    origins, dirs, hits = [], [], []
    for depth, (origin, rot) in zip(frames, poses, strict=True):
        d = depth[::SAMPLE_PIXEL_STEP, ::SAMPLE_PIXEL_STEP].reshape(-1).astype(np.float64)
        origins.append(np.broadcast_to(origin, (len(d), 3)))
        dirs.append((rays / norms[:, None]) @ rot.T)
        hits.append(np.where(np.isfinite(d), d * norms, np.inf))
    origins, dirs, hits = np.concatenate(origins), np.concatenate(dirs), np.concatenate(hits)
    surface, _ = acc.ray_samples(origins, dirs, hits, max_range, res, [], res)
    # Free space is what a reading shows: rays with no return (sky, beyond the camera's reach)
    # clear nothing in any mapper, so they give no free points.
    read = np.flatnonzero(np.isfinite(hits))
    pick = np.random.default_rng(seed).choice(read, min(FREE_RAYS, len(read)), replace=False)
    _, free = acc.ray_samples(origins[pick], dirs[pick], hits[pick], max_range, res, shapes, res)
    return surface, free


def with_range_noise(frames, sigma_at_1m: float, seed: int):
    """The frames with the emulated camera's range noise (firmware_sim.camera: a normal error of
    sigma_at_1m * depth^2, seeded); no return stays no return."""
    rng = np.random.default_rng(seed)
    return [(d + rng.standard_normal(d.shape) * sigma_at_1m * d * d).astype(np.float32) for d in frames]


# ------------------------------------------------------------------------------- scoring
def score_world(world_name: str, seed: int, run_out: Path, report: dict, frame_step: int,
                replay: bool = True, depth_noise: float = 0.0, mapper: dict | None = None) -> list[dict]:
    """Every drone of one run: surface metric of its own and global map, the replay beside it (unless
    replay is False: the daemons' maps only). depth_noise: range noise the replayed frames carry into
    both mappers (the truth samples come from the clean frames); mapper: coopd replay settings."""
    world = build_world(world_name, seed)
    config = MapperConfig()
    strict = {d["drone"]: d for d in report.get("accuracy", [])}
    flights, seen, rows = {}, {}, []
    for path in sorted(run_out.glob("flight_*.npz")):
        vid = int(path.stem.split("_")[1])
        f = flights[vid] = load_flight(path)
        cam = f["camera"]
        f["poses"] = camera_poses(flight_span(f["trajectory"]), cam, frame_step / cam.rate_hz)
        f["frames"] = render_frames(world, cam, f["poses"])
        seen[vid], f["free"] = truth_samples(f["frames"], f["poses"], cam, world.shapes, config.max_range,
                                             config.resolution, seed * 1000 + vid)
        if depth_noise > 0:
            f["frames"] = with_range_noise(f["frames"], depth_noise, seed * 1000 + vid)
    for vid, f in flights.items():
        row = {"world": world_name, "drone": vid, "members": f["members"],
               "replay_frames": len(f["frames"]), "wall_s": round(report.get("elapsed_s", 0.0))}
        for which in ("local", "global"):
            path = run_out / f"{which}_{vid}.cmap"
            if not path.exists():
                continue
            grid, _ = load_cmap(path)
            members = [vid] if which == "local" else [m for m in f["members"] if m in seen]
            points = np.concatenate([seen[m] for m in members])
            row[which] = acc.surface_accuracy(grid, f["world_from_map"], world.shapes, points)
            row[which]["free"] = acc.free_share(grid, f["world_from_map"], f["free"])
            row[which]["strict"] = {k: (strict.get(vid) or {}).get(which, {}).get(k)
                                    for k in ("precision", "recall", "precision_tol1", "recall_tol1")}
        for name, grid, frame in () if not replay else (
                ("coopd", replay_coopd(f["frames"], f["poses"], f["camera"], "clear", mapper), np.eye(4)),
                ("coopd_drop", replay_coopd(f["frames"], f["poses"], f["camera"], "drop", mapper), np.eye(4)),
                ("octomap", *replay_octomap(f["frames"], f["poses"], f["camera"], config))):
            row[name] = acc.surface_accuracy(grid, frame, world.shapes, seen[vid])
            row[name]["free"] = acc.free_share(grid, frame, f["free"])
        rows.append(round_floats(row))
    own = {r["drone"]: r.get("local") for r in rows}
    for r in rows:
        r["goal"] = goal_checks(r, [own.get(m) for m in r["members"]])
    return rows


def round_floats(v):
    if isinstance(v, float):
        return round(v, 4)
    if isinstance(v, dict):
        return {k: round_floats(x) for k, x in v.items()}
    return v


def goal_checks(r: dict, member_own: list) -> dict:
    """Which parts of the goal one drone's row meets."""
    def good(m):
        return bool(m) and m["surface_precision"] >= GOAL["surface_precision"] \
            and m["surface_recall"] >= GOAL["surface_recall"]

    g = r.get("global")
    members = [m for m in member_own if m]
    return {
        "own": good(r.get("local")),
        "global": good(g),
        "global_vs_members": bool(g and members) and all(
            g[k] >= min(m[k] for m in members) - GOAL["global_vs_members"]
            for k in ("surface_precision", "surface_recall")),
    } | ({} if "coopd" not in r else {  # without the replay there is nothing to compare with OctoMap
        "coopd_vs_octomap": all(r["coopd"][k] >= r["octomap"][k]
                                for k in ("surface_precision", "surface_recall"))})


# ------------------------------------------------------------------------------- tables
def fmt(v, spec: str) -> str:
    return "-" if v is None else format(v, spec)


def pr(m: dict | None) -> str:
    return "-" if not m else f"{fmt(m['surface_precision'], '.3f')} / {fmt(m['surface_recall'], '.3f')}"


def dist(m: dict | None) -> str:
    return "-" if not m else f"{fmt(m['surface_mean_m'], '.3f')} / {fmt(m['surface_p95_m'], '.3f')}"


def markdown(rows: list[dict]) -> str:
    """The tables for docs/accuracy.md: the daemons' maps, then the replay."""
    yes = {True: "yes", False: "no"}
    lines = ["| world | drone | own map P / R | own mean / p95 m | global P / R | global mean / p95 m "
             "| strict voxel P / R (global) | goal own / global / global vs members |",
             "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        s, gl = (r.get("global") or {}).get("strict") or {}, r["goal"]
        lines.append(f"| {r['world']} | {r['drone']} | {pr(r.get('local'))} | {dist(r.get('local'))} "
                     f"| {pr(r.get('global'))} | {dist(r.get('global'))} "
                     f"| {fmt(s.get('precision'), '.3f')} / {fmt(s.get('recall'), '.3f')} "
                     f"| {yes[gl['own']]} / {yes[gl['global']]} / {yes[gl['global_vs_members']]} |")
    replayed = [r for r in rows if "coopd" in r]
    if not replayed:
        return "\n".join(lines) + "\n"
    lines += ["", "| world | drone | frames | coopd P / R | coopd mean / p95 m | OctoMap P / R "
              "| OctoMap mean / p95 m | coopd ≥ OctoMap | free: coopd clear / drop / OctoMap |",
              "|---|---|---|---|---|---|---|---|---|"]
    for r in replayed:
        free = " / ".join(f"{r[k]['free']:.3f}" for k in ("coopd", "coopd_drop", "octomap"))
        lines.append(f"| {r['world']} | {r['drone']} | {r['replay_frames']} | {pr(r['coopd'])} "
                     f"| {dist(r['coopd'])} | {pr(r['octomap'])} | {dist(r['octomap'])} "
                     f"| {yes[r['goal']['coopd_vs_octomap']]} | {free} |")
    return "\n".join(lines) + "\n"


def meets_goal(r: dict) -> bool:
    return all(r["goal"].values())


FIXED_IN_REPLAY = ("resolution", "min_range", "max_range", "beyond_max_range", "growth")
"""MapperConfig fields --mapper may not change: the truth samples and OctoMap use the same resolution
and ranges, and the replay maps both beyond_max_range choices itself."""


def mapper_settings(text: str) -> dict:
    """--mapper's KEY=VALUE,... as MapperConfig fields of their own types; ValueError or TypeError
    on an unknown or fixed field or a value of the wrong kind."""
    out = overrides(text, MapperConfig(), FIXED_IN_REPLAY)
    MapperConfig(**out)
    return out


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--worlds", default=",".join(GENERATORS))
    p.add_argument("--drones", type=int, default=3)
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--speed", type=float, default=2.0)
    p.add_argument("--out", type=Path, default=ROOT / "out" / "bench")
    p.add_argument("--demo-timeout", type=float, default=900.0,
                   help="wall seconds a demo may take to start, fly and land (then reports what there is)")
    p.add_argument("--frame-step", type=int, default=FRAME_STEP, help="replay every n-th camera frame")
    p.add_argument("--autopilot", choices=("px4", "ardupilot"), default="px4")
    p.add_argument("--network", choices=("auto", "netns", "loopback"), default="auto",
                   help="the demo's network; loopback with its own --port-base runs beside another swarm "
                        "(two netns swarms share the FC cables' root-side addresses)")
    p.add_argument("--port-base", type=int, default=None, help="the demo's --port-base")
    p.add_argument("--tabulate", action="store_true", help="no flights: score the runs already there")
    p.add_argument("--no-replay", action="store_true",
                   help="score the daemons' maps only, no coopd/OctoMap replay (e.g. to compare autopilots)")
    p.add_argument("--depth-noise", type=float, default=0.0, metavar="SIGMA",
                   help="replayed frames carry range noise SIGMA * depth^2 (m; 0.01 is a RealSense D435's "
                        "2 %% at 2 m) into both mappers")
    p.add_argument("--mapper", default="", metavar="KEY=VALUE,...",
                   help="coopd replay settings (MapperConfig fields), e.g. miss_decrement=5")
    a = p.parse_args()
    try:
        mapper = mapper_settings(a.mapper)
    except (ValueError, TypeError) as e:
        p.error(f"--mapper: {e}")
    if a.depth_noise < 0:
        p.error("--depth-noise must not be negative")
    flights = "accuracy" if a.autopilot == "px4" else f"accuracy-{a.autopilot}"
    name = flights + (f"-noise{a.depth_noise:g}" if a.depth_noise else "") + "".join(
        f"-{k}{v}" for k, v in mapper.items())
    worlds = [w for w in a.worlds.split(",") if w]
    unknown = sorted(set(worlds) - set(GENERATORS))
    if unknown:
        p.error(f"unknown worlds {unknown}; known: {sorted(GENERATORS)}")
    a.out.mkdir(parents=True, exist_ok=True)
    rows = []
    for world in worlds:
        print(f"accuracy: {world} ...", flush=True)
        run_out = a.out / flights / world
        run_out.mkdir(parents=True, exist_ok=True)
        report = run_demo(world, a, run_out)
        if report is None:
            continue
        world_rows = score_world(world, a.seed, run_out, report, a.frame_step, replay=not a.no_replay,
                                 depth_noise=a.depth_noise, mapper=mapper)
        print(markdown(world_rows), flush=True)
        rows += world_rows
        (a.out / f"{name}.json").write_text(json.dumps(
            {"goal": GOAL, "autopilot": a.autopilot, "drones": a.drones, "seed": a.seed, "speed": a.speed,
             "frame_step": a.frame_step, "depth_noise": a.depth_noise, "replay_mapper": mapper,
             "camera_reach_m": CAMERA_REACH_M, "rows": rows}, indent=1))
        (a.out / f"{name}.md").write_text(markdown(rows))
    print(markdown(rows))
    print(f"goal met by {sum(meets_goal(r) for r in rows)} of {len(rows)} drones")
    print(f"wrote {a.out / (name + '.json')} and {a.out / (name + '.md')}")
    return 0 if rows and all(meets_goal(r) for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())

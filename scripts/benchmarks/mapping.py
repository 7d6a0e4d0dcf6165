"""scripts/bench mapping: depth frames into the grid, coopd vs OctoMap in the same run.

Both map the same frames of a generated room (0.1 m cells, 5 m range): coopd from the depth
images, OctoMap (octomap-python's insertPointCloud) from the same valid points and origins.
OctoMap runs in a subprocess per OpenMP thread count so OMP_NUM_THREADS takes effect.
Prints JSON and writes out/bench/mapping.json.
"""

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from coopd.mapping import Intrinsics, Mapper, MapperConfig  # noqa: E402
from tests.synthetic_scenes import render_depth, room_scene, survey_poses  # noqa: E402

RES, MIN_R, MAX_R = 0.1, 0.2, 5.0


def make_frames(width, height, n_stations, yaw_steps):
    scene = room_scene(0)
    intr = Intrinsics.from_fov(width, height, 87.0)
    return intr, [(render_depth(scene, intr, p), p) for p in survey_poses(n_stations, yaw_steps)]


def valid_points(depth, intr, pose):
    """World-frame end points of the pixels coopd treats as rays (z in [min, max])."""
    sx, sy = intr.ray_slopes()
    z = depth.astype(np.float64)
    pts = np.stack([sx[None, :] * z, sy[:, None] * z, z], axis=-1).reshape(-1, 3)
    ok = (z.reshape(-1) >= MIN_R) & (z.reshape(-1) <= MAX_R)
    return pts[ok] @ pose.rotation().T + pose.position


def time_coopd(intr, frames, threads, passes, **settings):
    """Best-of-passes wall time to integrate all frames into a fresh grid; per-frame times. settings:
    MapperConfig fields other than the bench's own."""
    best, best_frames, grid = None, None, None
    config = MapperConfig(resolution=RES, min_range=MIN_R, max_range=MAX_R, threads=threads, **settings)
    for _ in range(passes):
        mapper = Mapper(config)
        mapper.integrate(frames[0][0], intr, frames[0][1])          # warm caches, not timed
        mapper = Mapper(config)
        per = []
        rays = 0
        t0 = time.perf_counter()
        for depth, pose in frames:
            t = time.perf_counter()
            rays += mapper.integrate(depth, intr, pose).rays
            per.append(time.perf_counter() - t)
        total = time.perf_counter() - t0
        mapper.close()
        if best is None or total < best:
            best, best_frames, grid = total, per, mapper.grid
    return best, np.array(best_frames), rays, grid


def octomap_worker(npz_path, passes):
    """Runs in a subprocess: insertPointCloud every frame, print best total seconds as JSON."""
    import octomap

    data = np.load(npz_path)
    n = int(data["n"])
    clouds = [data[f"p{i}"] for i in range(n)]
    origins = [data[f"o{i}"] for i in range(n)]
    best = None
    for _ in range(passes):
        tree = octomap.OcTree(RES)
        t0 = time.perf_counter()
        for pts, o in zip(clouds, origins, strict=True):
            tree.insertPointCloud(pts, o, maxrange=MAX_R)
        total = time.perf_counter() - t0
        best = total if best is None else min(best, total)
    print(json.dumps({"seconds": best, "leafs": int(tree.getNumLeafNodes())}))


def time_octomap(frames, intr, omp_threads, passes):
    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, "frames.npz")
        arrays = {"n": np.array(len(frames))}
        for i, (depth, pose) in enumerate(frames):
            arrays[f"p{i}"] = valid_points(depth, intr, pose)
            arrays[f"o{i}"] = pose.position
        np.savez(path, **arrays)
        env = dict(os.environ, OMP_NUM_THREADS=str(omp_threads))
        out = subprocess.run([sys.executable, __file__, "--octomap-worker", path, "--passes", str(passes)],
                             env=env, capture_output=True, text=True, check=True)
        return json.loads(out.stdout.strip().splitlines()[-1])["seconds"]


def jit_times():
    """Seconds to import and map one small frame: cold (empty numba cache) and warm (cache filled)."""
    code = (f"import time; t=time.perf_counter(); import sys; sys.path.insert(0, {str(ROOT)!r});"
            "from tests.synthetic_scenes import *; from coopd.mapping import *;"
            "i=Intrinsics.from_fov(32,24,87.0); p=survey_poses(1,1)[0];"
            "d=render_depth(room_scene(0), i, p); Mapper().integrate(d, i, p);"
            "print(time.perf_counter()-t)")
    with tempfile.TemporaryDirectory() as cache:
        env = dict(os.environ, NUMBA_CACHE_DIR=cache)
        runs = [float(subprocess.run([sys.executable, "-c", code], env=env, capture_output=True,
                                     text=True, check=True).stdout.strip()) for _ in range(2)]
    return {"cold_first_frame_s": round(runs[0], 2), "warm_cache_first_frame_s": round(runs[1], 2)}


def main():
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--octomap-worker")
    ap.add_argument("--passes", type=int, default=3)
    ap.add_argument("--quick", action="store_true", help="fewer frames, one pass (smoke run)")
    args = ap.parse_args()
    if args.octomap_worker:
        octomap_worker(args.octomap_worker, args.passes)
        return
    passes = 1 if args.quick else args.passes
    stations, yaws = (1, 4) if args.quick else (3, 8)
    results = {"bench": "mapping", "resolution_m": RES, "max_range_m": MAX_R, "sizes": []}
    for width, height in ((160, 120), (320, 240), (640, 480)):
        intr, frames = make_frames(width, height, stations, yaws)
        t1, per1, rays, grid1 = time_coopd(intr, frames, 1, passes)
        t2, per2, _, grid2 = time_coopd(intr, frames, 2, passes)
        t0, _, _, _ = time_coopd(intr, frames, 1, passes, graze_deg=0.0)
        o1 = time_octomap(frames, intr, 1, passes)
        o2 = time_octomap(frames, intr, 2, passes)
        def ms(seconds):
            return round(float(seconds) * 1e3, 2)

        n = len(frames)
        entry = {
            "frame": f"{width}x{height}", "frames": n, "rays": rays,
            "coopd_1thread": {"rays_per_s": round(rays / t1), "ms_per_frame_mean": ms(per1.mean()),
                              "ms_per_frame_p50": ms(np.median(per1)), "ms_per_frame_max": ms(per1.max())},
            "coopd_2threads": {"rays_per_s": round(rays / t2), "ms_per_frame_mean": ms(per2.mean()),
                               "identical_to_1thread": bool(grid1.same_cells(grid2))},
            "octomap_1thread": {"rays_per_s": round(rays / o1), "ms_per_frame_mean": ms(o1 / n)},
            "octomap_2threads": {"rays_per_s": round(rays / o2), "ms_per_frame_mean": ms(o2 / n)},
            "ratio_1thread_vs_octomap_1thread": round(o1 / t1, 2),
            "ratio_2threads_vs_octomap_1thread": round(o1 / t2, 2),
            "ratio_2threads_vs_octomap_2threads": round(o2 / t2, 2),
            # what sparing grazed surface cells (MapperConfig.graze_deg) costs: > 1 is slower
            "ratio_1thread_vs_no_graze_guard": round(t1 / t0, 2),
        }
        results["sizes"].append(entry)
    results["jit"] = jit_times()
    out = ROOT / "out" / "bench"
    out.mkdir(parents=True, exist_ok=True)
    (out / "mapping.json").write_text(json.dumps(results, indent=2))
    print(json.dumps(results, indent=2))


if __name__ == "__main__":
    main()

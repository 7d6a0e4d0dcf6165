"""Merge benchmark on worlds nobody tuned for: fresh generated worlds every run, the six as references.

Sets of pairs (firmware_sim/mergeset.py: two drones' ray-cast partial maps of 10 m boxes centred on
the world's loop, 3-16 m apart (as far as the loop reaches), each map in its own start frame; the
truth is exact; each start frame has any yaw and roll/pitch within +-3 deg, --max-tilt changes that):
- fresh: --worlds generated worlds `gen:SEED` (all parameters drawn from the seed), --per-world pairs
  each; the world seeds are drawn from --seed, itself new on every run unless given, and printed;
- reference: the six firmware_sim worlds (seed 0), --references pairs each, the same every run;
- benchset: firmware_sim/benchset.py's building, --pairs overlapping and --far far-apart pairs.
Fresh pairs are also merged with map B changed (--robust): mapped at 0.05 or 0.2 m instead of 0.1,
its drone started 1 m higher, 10 % of its known cells flipped.

Per merge: rotation error, the translation error at B's origin, and the mean and max displacement of
B's occupied cells between the estimated and the true transform. Success: accepted, rotation error
< 2 deg and mean displacement < 0.2 m; a wrong merge is accepted otherwise. Per overlap band: pairs,
successes, wrong merges, accepted within 0.05 m and beyond 0.15 m mean displacement. Open3D's global
registration (FPFH + RANSAC + ICP, which accepts all it returns) runs on the same base pairs when
installed. The goal (fresh base pairs): >= 90 % of pairs with overlap >= 0.3 accepted within 0.05 m,
no accepted pair beyond 0.15 m, 0 wrong, more successes than Open3D in every band.

Usage: scripts/bench merge [--seed S] [--worlds N] [--per-world K] [--references K] [--pairs N]
       [--far N] [--robust res0.05,res0.2,lift1,flip0.1] [--variants coopd] [--max-tilt DEG]
       [--no-open3d] [--out PATH] [--cache DIR]
Tables and CPU seconds per merge (median, p90, max) on stderr, JSON on stdout and in
out/bench/merge.json. The pairs depend only on the seed and
the counts, so --cache DIR keeps them (one .npz per set of arguments) and a repeated run skips the
ray-casting (a quarter of the run).
"""

import argparse
import hashlib
import io
import json
import secrets
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from coopd.geometry import apply, rotation_angle_deg  # noqa: E402
from coopd.grid import OccupancyGrid  # noqa: E402
from coopd.io.atomic import write_atomic  # noqa: E402
from coopd.merging.pair import merge_pair, prepare  # noqa: E402
from coopd.merging.params import VARIANTS, coopd_params  # noqa: E402
from coopd.merging.validation import agreement  # noqa: E402
from firmware_sim.benchset import MAX_TILT_DEG, benchmark_pairs  # noqa: E402
from firmware_sim.exploration import occupied_points  # noqa: E402
from firmware_sim.mergeset import displacement, world_pairs  # noqa: E402
from firmware_sim.worlds import GENERATORS, build_world  # noqa: E402

BANDS = [(0.0, 0.15), (0.15, 0.3), (0.3, 0.5), (0.5, 1.01)]
GOAL_BAND = (0.3, 1.01)
MAX_ROT_DEG = 2.0
MAX_DISPLACEMENT_M = 0.2
"""A merge is right when its rotation error and B's mean displacement are below these."""
SUBCELL_M, BEYOND_M = 0.05, 0.15
"""Goal: accepted within SUBCELL_M mean displacement, none beyond BEYOND_M."""
SHIFTS_M = (3.0, 16.0)
REFERENCE_SHIFTS_M = (4.0, 7.0, 10.0)
DISPLACEMENT_POINTS = 20000
ROBUST = "res0.05,res0.2,lift1,flip0.1"


def tilt_bound(text: str) -> float:
    """--max-tilt's value: degrees in 0..30 (0.0 and -0.0 alike)."""
    value = float(text)
    if not 0.0 <= value <= 30.0:
        raise argparse.ArgumentTypeError(f"{text} is not a tilt bound in 0..30 degrees")
    return abs(value)


def band_name(lo: float, hi: float) -> str:
    """'0.30-0.50', or '>=0.50' for the open top band."""
    return f">={lo:.2f}" if hi > 1.0 else f"{lo:.2f}-{hi:.2f}"


def errors(estimate: np.ndarray, truth: np.ndarray, b) -> dict:
    """Rotation error (and its tilt: the angle between the two transforms' vertical axes), translation
    error at B's origin, mean and max displacement of B's occupied cells, and their mean offset split
    into its horizontal and vertical parts."""
    points = occupied_points(b)
    points = points[:: max(1, len(points) // DISPLACEMENT_POINTS)]
    mean, worst = displacement(estimate, truth, points)
    turn = estimate[:3, :3].T @ truth[:3, :3]
    rot = rotation_angle_deg(turn)
    tilt = float(np.degrees(np.arccos(np.clip(turn[2, 2], -1.0, 1.0))))
    trans = float(np.linalg.norm(estimate[:3, 3] - truth[:3, 3]))
    offset = (apply(estimate, points) - apply(truth, points)).mean(axis=0) if len(points) else np.zeros(3)
    return {"rot_err_deg": round(rot, 3), "tilt_err_deg": round(tilt, 3), "trans_err_m": round(trans, 3),
            "mean_disp_m": round(mean, 4), "max_disp_m": round(worst, 4),
            "offset_h_m": round(float(np.hypot(offset[0], offset[1])), 4),
            "offset_v_m": round(float(abs(offset[2])), 4),
            "correct": bool(rot < MAX_ROT_DEG and mean < MAX_DISPLACEMENT_M)}


def error_split(rows: list[dict]) -> dict | None:
    """Ranges of the error's parts over coopd's right merges of fresh base pairs at overlap >= 0.3."""
    ok = [r for r in rows if r["method"] == "coopd" and r["set"] == "fresh" and r["variant"] == "base"
          and r["overlap"] >= 0.3 and r["accepted"] and r["correct"]]
    if not ok:
        return None
    return {k: [min(r[k] for r in ok), max(r[k] for r in ok)]
            for k in ("tilt_err_deg", "rot_err_deg", "offset_h_m", "offset_v_m")} | {"merges": len(ok)}


def open3d_register(a, b, voxel=0.3):
    """Open3D tutorial global registration: voxel downsample, FPFH, RANSAC on feature matches, ICP."""
    import open3d as o3d

    def cloud(g):
        pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(occupied_points(g)))
        pc = pc.voxel_down_sample(voxel)
        pc.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2 * voxel, max_nn=30))
        f = o3d.pipelines.registration.compute_fpfh_feature(
            pc, o3d.geometry.KDTreeSearchParamHybrid(radius=5 * voxel, max_nn=100))
        return pc, f

    reg = o3d.pipelines.registration
    src, fs = cloud(b)
    dst, fd = cloud(a)
    dist = 1.5 * voxel
    res = reg.registration_ransac_based_on_feature_matching(
        src, dst, fs, fd, True, dist, reg.TransformationEstimationPointToPoint(False), 3,
        [reg.CorrespondenceCheckerBasedOnEdgeLength(0.9), reg.CorrespondenceCheckerBasedOnDistance(dist)],
        reg.RANSACConvergenceCriteria(100000, 0.999))
    icp = reg.registration_icp(src, dst, 0.4 * voxel, res.transformation,
                               reg.TransformationEstimationPointToPlane())
    return np.asarray(icp.transformation)


def has_open3d() -> bool:
    """Whether Open3D is importable (it is optional)."""
    try:
        import open3d  # noqa: F401
    except ImportError:
        return False
    return True


def build_pairs(args, seed: int) -> list[dict]:
    """Every pair of the run: dicts with set, world, seed, variant, a, b, a_from_b, overlap."""
    rng = np.random.default_rng(seed)
    out = []

    def add(set_name, world, pair_seed, shift, variants):
        for p in world_pairs(world, pair_seed, shift, variants, max_tilt_deg=args.max_tilt):
            out.append({"set": set_name, "world": p.world, "seed": p.seed, "variant": p.variant, "a": p.a,
                        "b": p.b, "a_from_b": p.a_from_b, "overlap": p.overlap, "shift_m": round(shift, 2)})

    robust = [v for v in args.robust.split(",") if v]
    for world_seed in rng.integers(0, 1_000_000, args.worlds):
        world = build_world(f"gen:{int(world_seed)}")
        for _ in range(args.per_world):
            add("fresh", world, int(rng.integers(0, 2**31)), float(rng.uniform(*SHIFTS_M)), robust)
    for name in GENERATORS if args.references else ():
        world = build_world(name, 0)
        for k in range(args.references):
            add("reference", world, k + 1, REFERENCE_SHIFTS_M[k % len(REFERENCE_SHIFTS_M)], ())
    if args.pairs or args.far:
        for k, p in enumerate(benchmark_pairs(args.pairs, non_overlapping=args.far)):
            out.append({"set": "benchset", "world": "benchset", "seed": p.seed, "variant": "base", "a": p.a,
                        "b": p.b, "a_from_b": p.a_from_b, "overlap": p.overlap, "shift_m": None,
                        "far": k >= args.pairs})
    return out


PAIR_FIELDS = ("set", "world", "seed", "variant", "overlap", "shift_m", "far")
CACHE_VERSION = 1


def cache_path(args, seed: int) -> Path:
    """Where --cache keeps the pairs these arguments draw."""
    drawn = (CACHE_VERSION, seed, args.worlds, args.per_world, args.references, args.pairs, args.far,
             args.robust)
    if args.max_tilt != MAX_TILT_DEG:  # named only when changed: the caches of the default stay valid
        drawn += (("max_tilt", args.max_tilt),)
    return args.cache / f"merge_pairs-{hashlib.sha1(repr(drawn).encode()).hexdigest()[:12]}.npz"


def save_pairs(pairs: list[dict], path: Path) -> None:
    """The pairs as one .npz (grids stored once even when several pairs share map A), atomically."""
    grids: dict[int, int] = {}
    arrays = {}
    for k, p in enumerate(pairs):
        for side in ("a", "b"):
            g = p[side]
            if id(g) not in grids:
                n = grids[id(g)] = len(grids)
                arrays |= {f"g{n}_cells": g.cells, f"g{n}_offset": g.offset,
                           f"g{n}_res": np.float64(g.resolution)}
            arrays[f"p{k}_{side}"] = np.int64(grids[id(g)])
        arrays[f"p{k}_truth"] = p["a_from_b"]
    arrays["meta"] = np.array(json.dumps([{f: p[f] for f in PAIR_FIELDS if f in p} for p in pairs]))
    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_atomic(path, buf.getvalue())


def load_pairs(path: Path) -> list[dict]:
    """Pairs written by save_pairs (no pickle)."""
    with np.load(path, allow_pickle=False) as z:
        meta = json.loads(str(z["meta"]))
        grids = {}

        def grid(n: int) -> OccupancyGrid:
            if n not in grids:
                grids[n] = OccupancyGrid(z[f"g{n}_cells"].copy(), float(z[f"g{n}_res"]),
                                         z[f"g{n}_offset"].copy())
            return grids[n]

        return [m | {"a": grid(int(z[f"p{k}_a"])), "b": grid(int(z[f"p{k}_b"])),
                     "a_from_b": z[f"p{k}_truth"].copy()} for k, m in enumerate(meta)]


def run_coopd(pairs, name: str) -> list[dict]:
    """Merge every pair with one coopd variant; a row per pair."""
    params = VARIANTS[name]()
    rows = []
    for p in pairs:
        c = time.process_time()
        r = merge_pair(p["a"], p["b"], params)
        cpu = time.process_time() - c
        rows.append(row(p, name, r.accepted, r.transform) | {
            "score": round(r.score, 3), "reason": r.reason, "cpu_seconds": round(cpu, 3)})
    return rows


def run_open3d(pairs) -> list[dict]:
    """Open3D on the base pairs; 'validated' tells what coopd's validation would keep of its answers."""
    import open3d as o3d

    o3d.utility.random.seed(0)
    vparams = coopd_params()
    rows = []
    for p in pairs:
        if p["variant"] != "base":
            continue
        c = time.process_time()
        t = open3d_register(p["a"], p["b"])
        cpu = time.process_time() - c
        sa, sb = prepare(p["a"], vparams, lazy=True).summary, prepare(p["b"], vparams, lazy=True).summary
        ag = agreement(sa, sb, t)
        share = ag.agree / max(1, len(sa.sample_m) + len(sb.sample_m))
        validated = (ag.score >= vparams.min_score and ag.agree >= vparams.min_agreement
                     and share >= vparams.min_overlap)
        rows.append(row(p, "open3d", True, t) | {"validated": validated, "cpu_seconds": round(cpu, 3)})
    return rows


def row(p: dict, method: str, accepted: bool, transform: np.ndarray) -> dict:
    """The per-pair record: which pair, whether accepted, its errors."""
    return {"set": p["set"], "world": p["world"], "seed": p["seed"], "variant": p["variant"],
            "method": method, "overlap": round(p["overlap"], 3), "shift_m": p["shift_m"],
            "far": p.get("far", False),
            "accepted": bool(accepted)} | errors(transform, p["a_from_b"], p["b"])


def band_summary(rows: list[dict]) -> dict:
    """Per overlap band (and overlap >= 0.3): pairs, successes, wrong merges, displacement figures."""
    out = {}
    for lo, hi in BANDS + [GOAL_BAND]:
        sel = [r for r in rows if lo <= r["overlap"] < hi and not r["far"]]
        if not sel:
            continue
        ok = [r for r in sel if r["accepted"] and r["correct"]]
        accepted = [r for r in sel if r["accepted"]]
        out["overlap>=0.30" if (lo, hi) == GOAL_BAND else band_name(lo, hi)] = {
            "pairs": len(sel), "success": len(ok), "wrong": len(accepted) - len(ok),
            "within_0.05m": sum(r["mean_disp_m"] <= SUBCELL_M for r in ok),
            "beyond_0.15m": sum(r["mean_disp_m"] > BEYOND_M for r in accepted),
            "median_mean_disp_m": round(float(np.median([r["mean_disp_m"] for r in ok])), 4) if ok else None,
            "worst_mean_disp_m": round(max(r["mean_disp_m"] for r in ok), 4) if ok else None,
            "worst_max_disp_m": round(max(r["max_disp_m"] for r in ok), 4) if ok else None}
    far = [r for r in rows if r["far"]]
    if far:
        out["far apart"] = {"pairs": len(far), "false_accepts": sum(r["accepted"] for r in far)}
    return out


def summarise(rows: list[dict]) -> dict:
    """{set: {variant of B: {method: bands}}}."""
    out: dict = {}
    for r in rows:
        out.setdefault(r["set"], {}).setdefault(r["variant"], {}).setdefault(r["method"], []).append(r)
    return {s: {v: {m: band_summary(rs) for m, rs in ms.items()} for v, ms in vs.items()}
            for s, vs in out.items()}


def goal(summary: dict, method: str = "coopd") -> dict:
    """The fresh-world goal, each part with its measured figure."""
    fresh = summary.get("fresh", {}).get("base", {})
    bands = fresh.get(method, {})
    top = bands.get("overlap>=0.30")
    if not top:
        return {"evaluated": False}
    within = top["within_0.05m"] / top["pairs"]
    all_bands = [b for b in bands if b not in ("overlap>=0.30", "far apart")]
    beyond = sum(bands[b]["beyond_0.15m"] for b in all_bands)
    wrong = sum(bands[b]["wrong"] for b in all_bands)
    o3d = fresh.get("open3d")
    beats = {b: (bands[b]["success"], o3d[b]["success"]) for b in all_bands if o3d and b in o3d}
    return {"evaluated": True,
            "share_overlap_ge_0.3_within_0.05m": round(within, 3), "share_met": within >= 0.9,
            "accepted_beyond_0.15m": beyond, "wrong": wrong,
            "successes_vs_open3d_per_band": beats or None,
            "beats_open3d_every_band": all(c > o for c, o in beats.values()) if beats else None}


def cpu_summary(rows: list[dict]) -> dict:
    """Per method: merges, median, 90th percentile and largest CPU seconds per merge."""
    out = {}
    for method in dict.fromkeys(r["method"] for r in rows):
        cpu = np.array([r["cpu_seconds"] for r in rows if r["method"] == method])
        out[method] = {"merges": len(cpu), "median": round(float(np.median(cpu)), 3),
                       "p90": round(float(np.percentile(cpu, 90)), 3), "max": round(float(cpu.max()), 3)}
    return out


def table(summary: dict) -> str:
    """The per-band tables, one line per set, B variant, method and band."""
    head = (f"{'set':<9} {'B':<8} {'method':<7} {'overlap':<13} {'pairs':>5} {'success':>7} {'wrong':>5} "
            f"{'<=0.05m':>7} {'>0.15m':>6} {'median':>7} {'worst':>6} {'max':>6}")
    lines = [head]
    for s, vs in summary.items():
        for v, ms in vs.items():
            for m, bands in ms.items():
                for b, f in bands.items():
                    lead = f"{s:<9} {v:<8} {m:<7} {b:<13} {f['pairs']:>5}"
                    if b == "far apart":
                        lines.append(f"{lead} false accepts {f['false_accepts']}")
                        continue
                    disp = [f[k] for k in ("median_mean_disp_m", "worst_mean_disp_m", "worst_max_disp_m")]
                    d = [f"{x:.3f}" if x is not None else "-" for x in disp]
                    lines.append(f"{lead} {f['success']:>7} {f['wrong']:>5} {f['within_0.05m']:>7} "
                                 f"{f['beyond_0.15m']:>6} {d[0]:>7} {d[1]:>6} {d[2]:>6}")
    return "\n".join(lines)


def parse_args(argv=None):
    ap = argparse.ArgumentParser(prog="scripts/bench merge", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seed", type=int, default=None, help="draws the fresh worlds and pairs (default: new)")
    ap.add_argument("--worlds", type=int, default=8, help="fresh generated worlds")
    ap.add_argument("--per-world", type=int, default=4, help="pairs per fresh world")
    ap.add_argument("--references", type=int, default=2, help="pairs per reference world (0: none)")
    ap.add_argument("--pairs", type=int, default=0, help="overlapping pairs of benchset's building")
    ap.add_argument("--far", type=int, default=10,
                    help="far-apart pairs of benchset's building (must be refused)")
    ap.add_argument("--robust", default=ROBUST, help="B variants merged for every fresh pair ('' for none)")
    ap.add_argument("--variants", default="coopd", help=f"coopd variants ({', '.join(VARIANTS)})")
    ap.add_argument("--max-tilt", type=tilt_bound, default=MAX_TILT_DEG,
                    help="roll/pitch bound (deg) of the fresh and reference pairs' start frames (0: level)")
    ap.add_argument("--no-open3d", action="store_true")
    ap.add_argument("--out", type=Path, default=Path("out/bench/merge.json"),
                    help="the JSON report; an existing directory gets merge.json in it")
    ap.add_argument("--cache", type=Path, default=None,
                    help="directory keeping the pairs between runs with the same seed and counts")
    args = ap.parse_args(argv)
    for v in filter(None, args.variants.split(",")):
        if v not in VARIANTS:
            ap.error(f"unknown variant {v!r}")
    if min(args.worlds, args.per_world, args.references, args.pairs, args.far) < 0:
        ap.error("counts must not be negative")
    if args.out.is_dir():  # known now, not after the whole run
        args.out = args.out / "merge.json"
    return args


def main(argv=None) -> dict:
    args = parse_args(argv)
    seed = args.seed if args.seed is not None else secrets.randbelow(1_000_000)
    print(f"merge bench: --seed {seed} (repeat this run with it)", file=sys.stderr)
    t0 = time.perf_counter()
    cached = cache_path(args, seed) if args.cache else None
    if cached is not None and cached.exists():
        pairs = load_pairs(cached)
        print(f"  pairs from {cached}", file=sys.stderr)
    else:
        pairs = build_pairs(args, seed)
        if cached is not None:
            save_pairs(pairs, cached)
    gen_s = time.perf_counter() - t0
    worlds = sorted({p["world"] for p in pairs if p["set"] == "fresh"})
    for w in worlds:
        print(f"  fresh world {w}", file=sys.stderr)
    rows = []
    if pairs:
        first = VARIANTS[next(v for v in args.variants.split(",") if v)]()
        merge_pair(pairs[0]["a"], pairs[0]["b"], first)  # compile the numba kernels off the clock
    for name in filter(None, args.variants.split(",")):
        rows += run_coopd(pairs, name)
    open3d = not args.no_open3d and has_open3d()
    if open3d:
        rows += run_open3d(pairs)
    summary = summarise(rows)
    command = "scripts/bench merge " + " ".join(sys.argv[1:] if argv is None else argv)
    report = {"seed": seed, "command": command,
              "fresh_worlds": worlds, "pairs": len(pairs), "generation_seconds": round(gen_s, 1),
              "open3d": open3d, "goal": goal(summary), "cpu_seconds_per_merge": cpu_summary(rows),
              "error_split": error_split(rows), "summary": summary, "rows": rows}
    print(table(summary), file=sys.stderr)
    print("goal (fresh worlds, coopd):", json.dumps(report["goal"]), file=sys.stderr)
    for method, cpu in report["cpu_seconds_per_merge"].items():
        print(f"CPU s per merge, {method}: median {cpu['median']:.3f}, p90 {cpu['p90']:.3f}, "
              f"max {cpu['max']:.3f} ({cpu['merges']} merges)", file=sys.stderr)
    if report["error_split"]:
        e = report["error_split"]
        print(f"error of the {e['merges']} right fresh base merges at overlap >= 0.3: tilt "
              f"{e['tilt_err_deg'][0]:.2f}-{e['tilt_err_deg'][1]:.2f} deg of rotation "
              f"{e['rot_err_deg'][0]:.2f}-{e['rot_err_deg'][1]:.2f} deg; mean offset horizontal "
              f"{e['offset_h_m'][0]:.3f}-{e['offset_h_m'][1]:.3f} m, vertical "
              f"{e['offset_v_m'][0]:.3f}-{e['offset_v_m'][1]:.3f} m", file=sys.stderr)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    write_atomic(args.out, json.dumps(report, indent=1).encode())
    print(json.dumps({k: v for k, v in report.items() if k != "rows"}, indent=1))
    return report


if __name__ == "__main__":
    main()

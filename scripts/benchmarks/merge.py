"""Merge benchmark: the same generated pairs through coopd's variants and Open3D's global registration.

Prints JSON and writes out/bench/merge.json. Success: rotation error < 2 deg and translation error
< 0.2 m; a wrong merge is an accepted transform outside that tolerance (Open3D accepts everything it
returns, so each of its failures is a wrong merge; 'open3d+validation' shows what coopd's validation
would have kept of them). Usage: scripts/bench merge [--pairs N] [--far N] [--variants a,b] [--no-open3d]
"""

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from coopd.geometry import rotation_angle_deg  # noqa: E402
from coopd.merging.pair import merge_pair, prepare  # noqa: E402
from coopd.merging.params import VARIANTS, coopd_params  # noqa: E402
from coopd.merging.validation import agreement  # noqa: E402
from firmware_sim.benchset import benchmark_pairs  # noqa: E402

BANDS = [(0.0, 0.1), (0.1, 0.2), (0.2, 0.3), (0.3, 0.4), (0.4, 0.5), (0.5, 0.6), (0.6, 1.01)]


def errors(t, truth):
    return (rotation_angle_deg(t[:3, :3].T @ truth[:3, :3]), float(np.linalg.norm(t[:3, 3] - truth[:3, 3])))


def open3d_register(a, b, voxel=0.3):
    """Open3D tutorial global registration: voxel downsample, FPFH, RANSAC on feature matches, ICP."""
    import open3d as o3d

    def cloud(g):
        pts = (np.argwhere(g.cells >= 50) + g.offset) * g.resolution
        pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
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


def summarise_rows(rows, accepted_key="accepted"):
    out = {}
    for lo, hi in BANDS + [(0.3, 1.01), (0.2, 1.01)]:
        sel = [r for r in rows if lo <= r["overlap"] < hi]
        if not sel:
            continue
        key = f"{lo:.1f}-{min(hi, 1.0):.1f}"
        ok = sum(r[accepted_key] and r["correct"] for r in sel)
        wrong = sum(r[accepted_key] and not r["correct"] for r in sel)
        out[key] = {"pairs": len(sel), "success": ok, "success_rate": round(ok / len(sel), 3),
                    "wrong": wrong, "wrong_rate": round(wrong / len(sel), 3)}
    return out


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--pairs", type=int, default=40)
    ap.add_argument("--far", type=int, default=10)
    ap.add_argument("--variants", default="coopd,thesis,features")
    ap.add_argument("--no-open3d", action="store_true")
    args = ap.parse_args()
    t0 = time.perf_counter()
    pairs = benchmark_pairs(args.pairs, non_overlapping=args.far)
    gen_s = time.perf_counter() - t0
    report = {"pairs": len(pairs), "generation_seconds": round(gen_s, 1),
              "map_shapes": [list(p.a.shape) for p in pairs[:3]],
              "overlaps": [round(p.overlap, 3) for p in pairs], "variants": {}}
    names = [v for v in args.variants.split(",") if v]
    merge_pair(pairs[0].a, pairs[0].b, VARIANTS[names[0]]())  # compile the numba kernels off the clock
    for name in names:
        params = VARIANTS[name]()
        merge_pair(pairs[0].a, pairs[0].b, params)
        rows = []
        for p in pairs:
            t, c = time.perf_counter(), time.process_time()
            r = merge_pair(p.a, p.b, params)
            dt, cpu = time.perf_counter() - t, time.process_time() - c
            re, te = errors(r.transform, p.a_from_b)
            rows.append({"overlap": p.overlap, "accepted": r.accepted, "correct": re < 2.0 and te < 0.2,
                         "rot_err_deg": round(re, 3), "trans_err_m": round(te, 3), "score": round(r.score, 3),
                         "inliers": r.inliers, "overlap_measured": round(r.overlap, 3),
                         "seconds": round(dt, 3),
                         "cpu_seconds": round(cpu, 3), "reason": r.reason})
        report["variants"][name] = summary(rows)
        print(name, json.dumps(report["variants"][name]["overall"]), file=sys.stderr)
    if not args.no_open3d:
        import open3d as o3d

        o3d.utility.random.seed(0)
        vparams = coopd_params()
        rows = []
        for p in pairs:
            t, c = time.perf_counter(), time.process_time()
            tr = open3d_register(p.a, p.b)
            dt, cpu = time.perf_counter() - t, time.process_time() - c
            re, te = errors(tr, p.a_from_b)
            sa, sb = prepare(p.a, vparams).summary, prepare(p.b, vparams).summary
            ag = agreement(sa, sb, tr)
            share = ag.agree / max(1, len(sa.sample_m) + len(sb.sample_m))
            validated = (ag.score >= vparams.min_score and ag.agree >= vparams.min_agreement
                         and share >= vparams.min_overlap)
            rows.append({"overlap": p.overlap, "accepted": True, "validated": validated,
                         "correct": re < 2.0 and te < 0.2, "rot_err_deg": round(re, 3),
                         "trans_err_m": round(te, 3), "score": round(ag.score, 3), "seconds": round(dt, 3),
                         "cpu_seconds": round(cpu, 3)})
        report["variants"]["open3d"] = summary(rows)
        report["variants"]["open3d+validation"] = {"bands": summarise_rows(rows, "validated")}
        print("open3d", json.dumps(report["variants"]["open3d"]["overall"]), file=sys.stderr)
    out = Path("out/bench/merge.json")
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(report, indent=1))
    print(json.dumps(report, indent=1))


def summary(rows):
    overlapping = [r for r in rows if r["overlap"] >= 0.1]
    far = [r for r in rows if r["overlap"] < 0.1]
    secs = [r["seconds"] for r in rows]
    cpu = [r["cpu_seconds"] for r in rows]
    return {
        "overall": {
            "success_rate_overlap_ge_0.3": summarise_rows(rows).get("0.3-1.0", {}).get("success_rate"),
            "wrong_merge_rate": round(sum(r["accepted"] and not r["correct"] for r in rows) / len(rows), 3),
            "false_accept_rate_non_overlapping": (round(sum(r["accepted"] for r in far) / len(far), 3)
                                                  if far else None),
            "success_rate_all_overlapping": round(sum(r["accepted"] and r["correct"] for r in overlapping)
                                                  / max(1, len(overlapping)), 3),
            "median_seconds": round(float(np.median(secs)), 3), "max_seconds": round(float(np.max(secs)), 3),
            "median_cpu_seconds": round(float(np.median(cpu)), 3),
        },
        "bands": summarise_rows(rows), "rows": rows,
    }


if __name__ == "__main__":
    main()

"""The thesis' merge experiment (ch. 10) reproduced on firmware_sim's six worlds, per pair and per stage.

Input (firmware_sim/exploration.py): per world two whole-building explorations ray-cast from the
world's ground truth, map B's frame turned 180 deg and 7-10 m away from A's, merged both ways (the
12 pairs of Table 5), and copies of each world's map A turned by 37/90/180 deg and shifted a few
metres, with 0/2/5/10 % of known cells flipped. Every truth is exact.

Per pair and variant, the thesis' own figures: keypoints detected and kept (Figs. 44, 48),
repeatability (Fig. 47: keypoints of a map re-detected within 2 downsampled cells in a copy turned
by a random yaw; per pair: keypoints of A re-detected in B under the truth), correspondences in
(matches) and out (RANSAC inliers of the best hypothesis) and how many are true (the truth carries
B's keypoint within 2 downsampled cells of A's), seconds per stage, success (rotation error < 2 deg,
translation error < 0.2 m and mean displacement of B's occupied cells <= 0.1 m, accepted), wrong
merges (accepted, not a success), CPU seconds per pair (both maps' features and the merge, process
time), and a PNG per pair: both maps after the merge, one colour each.

Usage: scripts/bench thesis [--variants coopd,thesis] [--set [variant:]key=value,...]
       [--worlds a,b] [--quick] [--angles 37,90,180] [--flips 0,0.02,0.05,0.1] [--no-png]
JSON in out/bench/thesis.json (--out), PNGs under out/bench/thesis/<variant>/ (--png-dir), a table on
stderr. --quick: 2 worlds, 1 angle, flips 0 and 0.10.
"""

import argparse
import dataclasses
import json
import re
import sys
import time
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import _overrides  # noqa: E402

from coopd.geometry import apply, invert, rigid, rotation_angle_deg, rotation_z  # noqa: E402
from coopd.grid import transform_grid  # noqa: E402
from coopd.io.atomic import write_atomic  # noqa: E402
from coopd.io.png import export_png_merge  # noqa: E402
from coopd.merging.features import extract  # noqa: E402
from coopd.merging.matching import match  # noqa: E402
from coopd.merging.pair import merge_prepared, prepare  # noqa: E402
from coopd.merging.params import VARIANTS, MergeParams  # noqa: E402
from coopd.merging.ransac import filter_correspondences  # noqa: E402
from firmware_sim import exploration  # noqa: E402
from firmware_sim.mergeset import displacement  # noqa: E402

QUICK_WORLDS = ("small_house", "bookstore")
QUICK_ANGLES = (90.0,)
QUICK_FLIPS = (0.0, 0.10)
MAX_ROT_DEG = 2.0
MAX_TRANS_M = 0.2
MAX_DISPLACEMENT_M = 0.1
TRUE_WITHIN_CELLS = 2.0
"""A keypoint is re-detected, a correspondence true, within this many downsampled cells."""
DISPLACEMENT_POINTS = 20000
PNG_MAX_CELLS = 3000
"""A merge PNG is skipped when the estimate throws map B this many cells wide (a wild transform)."""


def parse_value(text: str, default):
    """A --set value read as the type of the field's default (bool accepts true/false/1/0/yes/no)."""
    try:
        return _overrides.parse_value(text, default)
    except ValueError as e:
        raise SystemExit(f"--set: {e}") from None


def overrides(items: list[str], variants: list[str]) -> dict[str, dict]:
    """variant -> {field: value} from --set entries '[variant:]key=value,...' (no variant: all)."""
    known = {f.name: f for f in dataclasses.fields(MergeParams)}
    out: dict[str, dict] = {v: {} for v in variants}
    for item in items:
        target, _, text = item.rpartition(":")
        if target and target not in out:
            raise SystemExit(f"--set: variant {target!r} is not among --variants {','.join(variants)}")
        for pair in filter(None, text.split(",")):
            name, eq, value = pair.partition("=")
            name = name.strip()
            if not eq:
                raise SystemExit(f"--set: {pair!r} is not key=value")
            if name not in known:
                raise SystemExit(f"--set: MergeParams has no field {name!r} "
                                 f"(fields: {', '.join(sorted(known))})")
            for v in [target] if target else variants:
                out[v][name] = parse_value(value, getattr(VARIANTS[v](), name))
    return out


def variant_params(name: str, changes: dict) -> MergeParams:
    """The variant's preset with the overrides applied (dataclasses.replace: any field, present or new)."""
    if name not in VARIANTS:
        raise SystemExit(f"unknown variant {name!r}; choose from {', '.join(VARIANTS)}")
    return dataclasses.replace(VARIANTS[name](), **changes)


def errors(estimate: np.ndarray, truth: np.ndarray, b_points: np.ndarray) -> tuple[float, float, float]:
    """(rotation error deg, translation error m, mean displacement m of b's points between the two)."""
    rot = rotation_angle_deg(estimate[:3, :3].T @ truth[:3, :3])
    trans = float(np.linalg.norm(estimate[:3, 3] - truth[:3, 3]))
    return rot, trans, displacement(estimate, truth, b_points)[0]


def within(points: np.ndarray, targets: np.ndarray, radius: float) -> np.ndarray:
    """For each point, whether some target lies within radius."""
    if len(points) == 0 or len(targets) == 0:
        return np.zeros(len(points), dtype=bool)
    distance, _ = cKDTree(targets).query(points, distance_upper_bound=radius)
    return distance <= radius


def repeatability(fa, fb, a_from_b: np.ndarray) -> float | None:
    """Share of a's keypoints that, carried into b's frame by the truth, have one of b's within
    TRUE_WITHIN_CELLS downsampled cells (Fig. 47); None without keypoints."""
    if fa is None or fb is None or len(fa.points_m) == 0:
        return None
    hit = within(apply(invert(a_from_b), fa.points_m), fb.points_m, TRUE_WITHIN_CELLS * fa.cell_m)
    return round(float(hit.mean()), 4)


def correspondences(fa, fb, a_from_b: np.ndarray, params: MergeParams) -> dict | None:
    """Matches in and RANSAC inliers out (of the best hypothesis) and how many of each are true,
    through the same public stages and parameters the merge used."""
    if fa is None or fb is None:
        return None
    ia, ib, _ = match(fa.descriptors, fb.descriptors, params)
    radius = TRUE_WITHIN_CELLS * fa.cell_m
    true = np.linalg.norm(apply(a_from_b, fb.points_m[ib]) - fa.points_m[ia], axis=1) <= radius
    out = {"matches": int(len(ia)), "matches_true": int(true.sum()), "hypotheses": 0, "inliers": 0,
           "inliers_true": 0}
    if len(ia):
        tolerance_m = params.ransac_tolerance_cells * fa.cell_m
        hyps = filter_correspondences(fb.points_m[ib], fa.points_m[ia], tolerance_m, params)
        out["hypotheses"] = len(hyps)
        if hyps:
            out["inliers"] = hyps[0].inlier_count
            out["inliers_true"] = int((hyps[0].inliers & true).sum())
    return out


def keypoints(features) -> dict | None:
    """FAST 3D detections and keypoints kept after the filter (None: the variant has no features)."""
    if features is None:
        return None
    return {"detected": int(features.detected), "kept": int(len(features.points_m))}


def matrix(t: np.ndarray) -> list:
    """A 4x4 transform for JSON, row-major (b -> a, metres)."""
    return [[round(float(v), 9) for v in row] for row in t]


def yaw_deg(t: np.ndarray) -> float:
    return round(float(np.degrees(np.arctan2(t[1, 0], t[0, 0]))), 2)


class Variant:
    """One variant's parameters and its prepared maps (features computed once per map)."""

    def __init__(self, label: str, params: MergeParams):
        self.label = label
        self.params = params
        self.prepared: dict[int, tuple] = {}
        self.maps: dict[str, dict] = {}
        self.rows: list[dict] = []

    def prepare(self, grid):
        """(PreparedMap, CPU seconds, stage seconds) of a grid, once per grid object."""
        key = id(grid)
        if key not in self.prepared:
            tm: dict = {}
            c = time.process_time()
            p = prepare(grid, self.params, tm)
            self.prepared[key] = (grid, p, time.process_time() - c, tm)
        return self.prepared[key][1:]

    def map_figures(self, name: str, grid, seed: int) -> None:
        """Keypoints of a Table-5 map and their repeatability in a copy turned by a random yaw."""
        p, cpu, tm = self.prepare(grid)
        entry = {"keypoints": keypoints(p.features), "prepare_cpu_seconds": round(cpu, 3),
                 "stage_seconds": {k: round(v, 4) for k, v in tm.items()}}
        if p.features is not None:
            rng = np.random.default_rng(seed)
            heading = rng.uniform(0, 2 * np.pi)
            copy_from_map = rigid(rotation_z(rng.uniform(0, 2 * np.pi)),
                                  rng.uniform(1.0, 3.0) * np.array([np.cos(heading), np.sin(heading), 0.0]))
            turned = extract(transform_grid(grid, copy_from_map), self.params)
            entry["repeatability"] = {
                "yaw_deg": yaw_deg(copy_from_map),
                "share": repeatability(p.features, turned, invert(copy_from_map))}
        self.maps[name] = entry

    def run(self, pair, png_dir: Path | None) -> dict:
        """Merge one pair and measure it."""
        pa, cpu_a, tm_a = self.prepare(pair.a)
        pb, cpu_b, tm_b = self.prepare(pair.b)
        tm: dict = {}
        c = time.process_time()
        r = merge_prepared(pa, pb, self.params, tm)
        cpu = cpu_a + cpu_b + time.process_time() - c
        b_points = exploration.occupied_points(pair.b)
        b_points = b_points[:: max(1, len(b_points) // DISPLACEMENT_POINTS)]
        rot, trans, disp = errors(r.transform, pair.a_from_b, b_points)
        correct = rot < MAX_ROT_DEG and trans < MAX_TRANS_M and disp <= MAX_DISPLACEMENT_M
        stages: dict = {}
        for t in (tm_a, tm_b, tm):
            for k, v in t.items():
                stages[k] = stages.get(k, 0.0) + v
        row = {"pair": pair.name, "kind": pair.kind, "world": pair.world, "angle_deg": pair.angle_deg,
               "flip_fraction": pair.flip_fraction,
               "truth": {"yaw_deg": yaw_deg(pair.a_from_b),
                         "distance_m": round(float(np.linalg.norm(pair.a_from_b[:3, 3])), 3),
                         "transform": matrix(pair.a_from_b)},
               "transform": matrix(r.transform),
               "accepted": bool(r.accepted), "success": bool(r.accepted and correct),
               "wrong": bool(r.accepted and not correct), "rot_err_deg": round(rot, 3),
               "trans_err_m": round(trans, 3), "mean_displacement_m": round(disp, 3),
               "score": round(r.score, 4), "overlap": round(r.overlap, 4), "inliers": r.inliers,
               "reason": r.reason,
               "cpu_seconds": round(cpu, 3), "stage_seconds": {k: round(v, 4) for k, v in stages.items()},
               "keypoints": {"a": keypoints(pa.features), "b": keypoints(pb.features)},
               "repeatability": repeatability(pa.features, pb.features, pair.a_from_b),
               "correspondences": correspondences(pa.features, pb.features, pair.a_from_b, self.params),
               "png": None}
        if png_dir is not None:
            outcome = "success" if row["success"] else "wrong" if row["wrong"] else "refused"
            title = f"{self.label} {pair.name}: {outcome}"
            row["png"] = merge_png(pair, r.transform, png_dir / safe_name(self.label), title)
        self.rows.append(row)
        return row

    def totals(self) -> dict:
        """Per variant: Table-5 successes, turned-copy successes per flip level, wrong merges, CPU."""
        t5 = [r for r in self.rows if r["kind"] == "table5"]
        turned = [r for r in self.rows if r["kind"] == "turned"]
        cpu = [r["cpu_seconds"] for r in self.rows]
        corr = [r["correspondences"] for r in self.rows if r["correspondences"]]
        reps = [m["repeatability"]["share"] for m in self.maps.values()
                if m.get("repeatability") and m["repeatability"]["share"] is not None]

        def count(rows):
            return {"pairs": len(rows), "success": sum(r["success"] for r in rows),
                    "wrong": sum(r["wrong"] for r in rows), "accepted": sum(r["accepted"] for r in rows)}

        return {
            "table5": count(t5),
            "turned": {f"{f:g}": count([r for r in turned if r["flip_fraction"] == f])
                       for f in sorted({r["flip_fraction"] for r in turned})},
            "turned_all": count(turned),
            "wrong_merges": sum(r["wrong"] for r in self.rows),
            "median_cpu_seconds": round(float(np.median(cpu)), 3) if cpu else None,
            "max_cpu_seconds": round(float(np.max(cpu)), 3) if cpu else None,
            "repeatability_median": round(float(np.median(reps)), 4) if reps else None,
            "matches": sum(c["matches"] for c in corr) if corr else None,
            "matches_true": sum(c["matches_true"] for c in corr) if corr else None,
            "inliers": sum(c["inliers"] for c in corr) if corr else None,
            "inliers_true": sum(c["inliers_true"] for c in corr) if corr else None,
        }


def safe_name(text: str) -> str:
    """A file name made of text: runs of anything but letters, digits, '_', '.', '-' become '_'."""
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", text).strip("_")


def merge_png(pair, estimate: np.ndarray, directory: Path, title: str) -> str | None:
    """Both maps after the merge (B carried by the estimate), one colour each; None if the estimate
    is not a usable rigid transform or throws B far away."""
    lo, hi = pair.b.bounds_m()
    corners = np.array([[x, y, 0.0] for x in (lo[0], hi[0]) for y in (lo[1], hi[1])])
    moved = apply(estimate, corners) / pair.a.resolution
    a_lo, a_hi = pair.a.offset[:2], pair.a.offset[:2] + pair.a.shape[:2]
    span = np.maximum(moved.max(axis=0)[:2], a_hi) - np.minimum(moved.min(axis=0)[:2], a_lo)
    if not np.all(np.isfinite(span)) or span.max() > PNG_MAX_CELLS:
        return None
    directory.mkdir(parents=True, exist_ok=True)
    path = directory / (safe_name(pair.name.replace("<-", "-from-")) + ".png")
    try:
        export_png_merge(pair.a, pair.b, estimate, path, title)
    except ValueError:  # not a rigid transform
        return None
    return str(path)


HEADER = (f"{'variant':<10} {'pair':<34} {'ok':<7} {'rot°':>7} {'m':>6} {'disp':>6} {'kp a/b':>11} "
          f"{'rep':>5} {'match(t)':>12} {'inl(t)':>9} {'cpu s':>6}")


def row_line(label: str, r: dict) -> str:
    """One pair of one variant as a table line (t: how many are true)."""
    ka, kb = r["keypoints"]["a"], r["keypoints"]["b"]
    kp = f"{ka['kept']}/{kb['kept']}" if ka and kb else "-"
    c = r["correspondences"]
    mt = f"{c['matches']}({c['matches_true']})" if c else "-"
    it = f"{c['inliers']}({c['inliers_true']})" if c else "-"
    state = "OK" if r["success"] else "WRONG" if r["wrong"] else "refused"
    rep = f"{r['repeatability']:.2f}" if r["repeatability"] is not None else "-"
    return (f"{label:<10} {r['pair']:<34} {state:<7} {r['rot_err_deg']:>7.2f} {r['trans_err_m']:>6.2f} "
            f"{r['mean_displacement_m']:>6.2f} {kp:>11} {rep:>5} {mt:>12} {it:>9} {r['cpu_seconds']:>6.2f}")


def table(variants: list[Variant]) -> list[str]:
    """A readable summary: one line per pair and variant, then the totals."""
    lines = [HEADER] + [row_line(v.label, r) for v in variants for r in v.rows]
    for v in variants:
        t = v.totals()
        flips = ", ".join(f"{k}: {c['success']}/{c['pairs']}" for k, c in t["turned"].items())
        lines.append(f"{v.label}: Table 5 {t['table5']['success']}/{t['table5']['pairs']}, turned copies by "
                     f"flip level {flips}, wrong merges {t['wrong_merges']}, CPU s per pair median "
                     f"{t['median_cpu_seconds']} max {t['max_cpu_seconds']}, repeatability (random yaw) "
                     f"median {t['repeatability_median']}, matches {t['matches']} "
                     f"({t['matches_true']} true), inliers {t['inliers']} ({t['inliers_true']} true)")
    return lines


def floats(text: str) -> tuple[float, ...]:
    return tuple(float(v) for v in text.split(",") if v.strip())


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--variants", default="coopd,thesis")
    ap.add_argument("--set", action="append", default=[], metavar="[VARIANT:]KEY=VALUE,...",
                    help="MergeParams overrides, e.g. thesis:descriptor_steering=euler,ransac_model=rigid")
    ap.add_argument("--worlds", default=None, help=f"comma list of {','.join(exploration.WORLDS)}")
    ap.add_argument("--angles", default=None, help="turned copies' yaw angles, degrees (37,90,180)")
    ap.add_argument("--flips", default=None, help="turned copies' flipped fractions (0,0.02,0.05,0.1)")
    ap.add_argument("--quick", action="store_true", help="2 worlds, 1 angle, flips 0 and 0.10")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--cache-dir", default=str(exploration.CACHE_DIR))
    ap.add_argument("--out", default="out/bench/thesis.json")
    ap.add_argument("--png-dir", default="out/bench/thesis")
    ap.add_argument("--no-png", action="store_true")
    args = ap.parse_args(argv)
    names = [v for v in args.variants.split(",") if v]
    changes = overrides(args.set, names)
    variants = []
    for n in names:
        label = n + "".join(f"[{k}={v}]" for k, v in changes[n].items())
        variants.append(Variant(label, variant_params(n, changes[n])))
    worlds = tuple(w for w in (args.worlds.split(",") if args.worlds else
                               QUICK_WORLDS if args.quick else exploration.WORLDS) if w)
    unknown = [w for w in worlds if w not in exploration.WORLDS]
    if unknown:
        raise SystemExit(f"unknown worlds {unknown}; choose from {', '.join(exploration.WORLDS)}")
    angles = floats(args.angles) if args.angles else QUICK_ANGLES if args.quick else (37.0, 90.0, 180.0)
    flips = floats(args.flips) if args.flips else QUICK_FLIPS if args.quick else (0.0, 0.02, 0.05, 0.10)
    png_dir = None if args.no_png else Path(args.png_dir)
    report = {"set": {"worlds": list(worlds), "seed": args.seed, "angles_deg": list(angles),
                      "flips": list(flips), "route": dataclasses.asdict(exploration.Route()), "maps": {}},
              "criteria": {"max_rot_deg": MAX_ROT_DEG, "max_trans_m": MAX_TRANS_M,
                           "max_mean_displacement_m": MAX_DISPLACEMENT_M,
                           "true_within_cells": TRUE_WITHIN_CELLS},
              "variants": {}}
    generation = 0.0
    warm = False
    print(HEADER, file=sys.stderr)
    for wi, world in enumerate(worlds):
        t0 = time.perf_counter()
        pairs = exploration.table5_pairs((world,), args.seed, cache_dir=Path(args.cache_dir) if args.cache_dir
                                         else None)
        first = pairs[0]
        pairs += exploration.turned_copies(first.a, angles, flips, seed=args.seed * 100 + wi, world=world,
                                           name=f"{world}:A")
        generation += time.perf_counter() - t0
        report["set"]["maps"][f"{world}:A"] = list(first.a.shape)
        report["set"]["maps"][f"{world}:B"] = list(first.b.shape)
        for v in variants:
            if not warm:  # compile the numba kernels off the clock
                warm_variant = Variant(v.label, v.params)
                warm_variant.run(first, None)
            v.map_figures(f"{world}:A", first.a, args.seed * 100 + 2 * wi)
            v.map_figures(f"{world}:B", first.b, args.seed * 100 + 2 * wi + 1)
            for pair in pairs:
                v.run(pair, png_dir)
                print(row_line(v.label, v.rows[-1]), file=sys.stderr, flush=True)
            v.prepared.clear()  # this world's maps are done
        warm = True
    report["set"]["generation_seconds"] = round(generation, 2)
    for v in variants:
        report["variants"][v.label] = {"params": dataclasses.asdict(v.params), "totals": v.totals(),
                                       "maps": v.maps, "pairs": v.rows}
    report["table"] = table(variants)
    print("\n".join(report["table"]), file=sys.stderr)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    write_atomic(out, json.dumps(report, indent=1).encode())
    print(json.dumps({k: v["totals"] for k, v in report["variants"].items()}, indent=1))
    return report


if __name__ == "__main__":
    main()

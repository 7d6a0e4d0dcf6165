"""scripts/benchmarks/thesis.py: parameter overrides, the figures' definitions, and a bounded run."""

import importlib.util
import json
import math
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from coopd.geometry import rigid, rotation_angle_deg, rotation_z
from coopd.merging.features import MapFeatures
from firmware_sim import exploration

ROOT = Path(__file__).resolve().parents[2]
spec = importlib.util.spec_from_file_location("bench_thesis", ROOT / "scripts" / "benchmarks" / "thesis.py")
thesis = importlib.util.module_from_spec(spec)
spec.loader.exec_module(thesis)


def test_overrides_parse_as_the_field_type_per_variant_and_refuse_unknown_fields():
    got = thesis.overrides(["thesis:ransac_model=rigid,ransac_iterations=300", "refine=false"],
                           ["coopd", "thesis"])
    assert got == {"coopd": {"refine": False},
                   "thesis": {"ransac_model": "rigid", "ransac_iterations": 300, "refine": False}}
    params = thesis.variant_params("thesis", got["thesis"])
    assert params.ransac_model == "rigid" and params.ransac_iterations == 300 and params.refine is False
    with pytest.raises(SystemExit, match="no field 'no_such_field'"):
        thesis.overrides(["no_such_field=1"], ["coopd"])
    with pytest.raises(SystemExit, match="not a boolean"):
        thesis.overrides(["refine=maybe"], ["coopd"])
    with pytest.raises(SystemExit, match="not among --variants"):
        thesis.overrides(["features:refine=true"], ["coopd"])
    with pytest.raises(SystemExit, match="is not a int"):
        thesis.overrides(["ransac_iterations=many"], ["coopd"])


def test_errors_measure_b_s_points_displacement_between_estimate_and_truth():
    truth = rigid(rotation_z(math.radians(180)), [9.0, 0.0, 0.0])
    points = np.array([[10.0, 0, 0], [-10.0, 0, 0], [0, 10.0, 0], [0, -10.0, 0]])
    rot, trans, disp = thesis.errors(truth, truth, points)
    assert rot < 1e-6 and trans == 0.0 and disp == 0.0
    turned = truth @ rigid(rotation_z(math.radians(1.0)))  # 1 deg about b's origin: 0.17 m at 10 m
    rot, trans, disp = thesis.errors(turned, truth, points)
    assert abs(rot - 1.0) < 1e-6 and trans < 1e-9 and abs(disp - 10 * 2 * math.sin(math.radians(0.5))) < 1e-6


def features(points):
    points = np.asarray(points, dtype=np.float64)
    n = len(points)
    return MapFeatures(points, np.zeros((n, 4), np.uint64), np.zeros((n, 3)), 0.2, n)


def test_repeatability_counts_keypoints_re_detected_within_two_cells_under_the_truth():
    a = features([[0, 0, 0], [1, 0, 0], [0, 1, 0], [5, 5, 1]])
    a_from_b = rigid(rotation_z(math.radians(90)), [2.0, 0.0, 0.0])
    b_from_a = np.linalg.inv(a_from_b)
    moved = np.c_[a.points_m, np.ones(4)] @ b_from_a.T
    b = features(np.vstack([moved[:2, :3] + [0.3, 0, 0], moved[2:3, :3] + [0.5, 0, 0]]))  # 0.3 in, 0.5 out
    assert thesis.repeatability(a, b, a_from_b) == 0.5
    assert thesis.repeatability(None, b, a_from_b) is None


@pytest.mark.slow
@pytest.mark.cpu_bound
def test_bounded_run_reports_every_pair_and_stage_and_its_truth_checks(tmp_path):
    out = tmp_path / "thesis.json"
    cache = tmp_path / "set"
    report = thesis.main(["--quick", "--cache-dir", str(cache), "--out", str(out),
                          "--png-dir", str(tmp_path / "png")])
    assert json.loads(out.read_text()) == json.loads(json.dumps(report))
    assert report["set"]["worlds"] == list(thesis.QUICK_WORLDS) and report["set"]["flips"] == [0.0, 0.1]
    assert set(report["variants"]) == {"coopd", "thesis"}
    truths = {p.name: p for w in thesis.QUICK_WORLDS for p in exploration.table5_pairs((w,), cache_dir=cache)}
    for name, v in report["variants"].items():
        rows = {r["pair"]: r for r in v["pairs"]}
        assert len(rows) == 8 and sum(r["kind"] == "table5" for r in rows.values()) == 4
        assert v["totals"]["table5"]["pairs"] == 4
        assert {k: c["pairs"] for k, c in v["totals"]["turned"].items()} == {"0": 2, "0.1": 2}
        table5 = [r for r in rows.values() if r["kind"] == "table5"]
        assert v["totals"]["table5"]["success"] == sum(r["success"] for r in table5)
        for r in rows.values():
            ok = r["rot_err_deg"] < 2 and r["trans_err_m"] < 0.2 and r["mean_displacement_m"] <= 0.1
            assert r["success"] == (r["accepted"] and ok) and r["wrong"] == (r["accepted"] and not ok)
            assert r["cpu_seconds"] > 0 and r["stage_seconds"]
            if r["png"]:
                assert Image.open(r["png"]).size[0] > 100
            if r["kind"] == "table5":  # the estimate in the JSON against the truth, rebuilt here
                truth = truths[r["pair"]].a_from_b
                assert np.allclose(r["truth"]["transform"], truth, atol=1e-5)
                est = np.array(r["transform"])
                assert abs(rotation_angle_deg(est[:3, :3].T @ truth[:3, :3]) - r["rot_err_deg"]) < 0.01
                assert abs(np.linalg.norm(est[:3, 3] - truth[:3, 3]) - r["trans_err_m"]) < 0.002
                assert abs(r["truth"]["yaw_deg"]) == 180.0 and 7.0 <= r["truth"]["distance_m"] <= 10.0
        # both variants merge every pair of the bounded set: the whole-building pairs turned 180
        # degrees, the lossless 90-degree copies and those with 10 % of their cells flipped
        failed = {p: (r["reason"], r["mean_displacement_m"]) for p, r in rows.items() if not r["success"]}
        assert not failed, (name, failed)
        if name == "coopd":
            assert all(r["keypoints"]["a"] is None and r["correspondences"] is None for r in rows.values())
        else:  # the feature variant: every stage timed, keypoints and correspondences counted
            for r in rows.values():
                assert {"preprocess", "fast3d", "filter", "orientation", "describe", "match", "ransac"} \
                    <= set(r["stage_seconds"])
                for side in "ab":
                    assert 0 <= r["keypoints"][side]["kept"] <= r["keypoints"][side]["detected"]
                c = r["correspondences"]
                assert 0 <= c["matches_true"] <= c["matches"] and 0 <= c["inliers_true"] <= c["inliers"]
                assert c["inliers"] <= c["matches"] and 0 <= r["repeatability"] <= 1
            shares = [m["repeatability"]["share"] for m in v["maps"].values()]
            assert all(s is None or 0 <= s <= 1 for s in shares) and any(s is not None for s in shares)
            assert sum(m["keypoints"]["kept"] for m in v["maps"].values()) > 0
    assert any(line.startswith("coopd: Table 5 ") for line in report["table"])

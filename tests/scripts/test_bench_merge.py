"""scripts/benchmarks/merge.py: per-band counting, the goal's arithmetic, and a bounded fresh-seed run."""

import importlib.util
import json
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
spec = importlib.util.spec_from_file_location("bench_merge", ROOT / "scripts" / "benchmarks" / "merge.py")
merge = importlib.util.module_from_spec(spec)
spec.loader.exec_module(merge)


def _row(overlap, accepted, correct, mean, method="coopd", far=False):
    return {"set": "fresh", "variant": "base", "method": method, "overlap": overlap, "accepted": accepted,
            "correct": correct, "mean_disp_m": mean, "max_disp_m": 2 * mean, "far": far}


def test_bands_count_successes_wrong_merges_and_displacements():
    rows = [_row(0.2, True, True, 0.04), _row(0.35, True, True, 0.03), _row(0.4, True, True, 0.12),
            _row(0.45, False, False, 3.0), _row(0.7, True, False, 1.5), _row(0.8, True, True, 0.16),
            _row(0.05, True, False, 9.0, far=True)]
    bands = merge.band_summary(rows)
    assert bands["0.15-0.30"] == {"pairs": 1, "success": 1, "wrong": 0, "within_0.05m": 1,
                                  "beyond_0.15m": 0, "median_mean_disp_m": 0.04, "worst_mean_disp_m": 0.04,
                                  "worst_max_disp_m": 0.08}
    assert bands["0.30-0.50"]["pairs"] == 3 and bands["0.30-0.50"]["success"] == 2
    assert bands["0.30-0.50"]["within_0.05m"] == 1 and bands["0.30-0.50"]["wrong"] == 0
    assert bands[">=0.50"] == {"pairs": 2, "success": 1, "wrong": 1, "within_0.05m": 0, "beyond_0.15m": 2,
                               "median_mean_disp_m": 0.16, "worst_mean_disp_m": 0.16,
                               "worst_max_disp_m": 0.32}
    assert bands["overlap>=0.30"]["pairs"] == 5 and bands["overlap>=0.30"]["within_0.05m"] == 1
    assert bands["far apart"] == {"pairs": 1, "false_accepts": 1}
    o3d = [_row(r["overlap"], True, r["overlap"] > 0.6, 0.1, "open3d") for r in rows if not r["far"]]
    goal = merge.goal(merge.summarise(rows + o3d))
    assert goal["share_overlap_ge_0.3_within_0.05m"] == 0.2 and goal["share_met"] is False
    assert goal["accepted_beyond_0.15m"] == 2 and goal["wrong"] == 1
    assert goal["successes_vs_open3d_per_band"] == {"0.15-0.30": (1, 0), "0.30-0.50": (2, 0),
                                                    ">=0.50": (1, 2)}
    assert goal["beats_open3d_every_band"] is False


def test_a_bounded_fresh_seed_run_prints_its_seed_and_repeats(tmp_path, capsys):
    argv = ["--seed", "5", "--worlds", "1", "--per-world", "1", "--references", "0", "--far", "0",
            "--robust", "flip0.1", "--no-open3d", "--out", str(tmp_path / "merge.json")]
    report = merge.main(argv)
    err = capsys.readouterr().err
    assert "--seed 5" in err and "fresh world gen:" in err and "overlap" in err
    assert report["seed"] == 5 and len(report["fresh_worlds"]) == 1 and report["pairs"] == 2
    rows = report["rows"]
    assert [r["variant"] for r in rows] == ["base", "flip0.1"]
    assert all(r["mean_disp_m"] <= r["max_disp_m"] for r in rows)
    assert json.loads((tmp_path / "merge.json").read_text())["summary"] == report["summary"]
    cpu = report["cpu_seconds_per_merge"]["coopd"]
    assert cpu["merges"] == 2 and 0 < cpu["median"] <= cpu["p90"] <= cpu["max"]
    assert "CPU s per merge, coopd: median" in err
    again = merge.main(argv)
    assert again["fresh_worlds"] == report["fresh_worlds"]
    assert [r["overlap"] for r in again["rows"]] == [r["overlap"] for r in rows]


def test_cached_pairs_give_the_same_run(tmp_path, capsys):
    """--cache: the first run keeps the pairs it drew, the second reads them back and merges the same maps."""
    argv = ["--seed", "5", "--worlds", "1", "--per-world", "1", "--references", "0", "--far", "0",
            "--robust", "flip0.1", "--no-open3d", "--out", str(tmp_path / "merge.json"),
            "--cache", str(tmp_path / "cache")]
    first = merge.main(argv)
    assert "pairs from" not in capsys.readouterr().err
    assert len(list((tmp_path / "cache").glob("merge_pairs-*.npz"))) == 1
    again = merge.main(argv)
    assert "pairs from" in capsys.readouterr().err
    keep = ("set", "world", "seed", "variant", "overlap", "shift_m", "far", "accepted", "rot_err_deg",
            "mean_disp_m", "max_disp_m", "score", "reason")
    def same(rows):
        return [{k: r[k] for k in keep} for r in rows]

    assert same(again["rows"]) == same(first["rows"])


def test_bad_arguments_are_refused():
    with pytest.raises(SystemExit):
        merge.parse_args(["--variants", "nonesuch"])
    with pytest.raises(SystemExit):
        merge.parse_args(["--worlds", "-1"])


def test_out_may_name_a_directory(tmp_path):
    """--out DIR writes DIR/merge.json (it used to fail after the whole run, renaming onto DIR)."""
    assert merge.parse_args(["--out", str(tmp_path)]).out == tmp_path / "merge.json"
    assert merge.parse_args(["--out", str(tmp_path / "x.json")]).out == tmp_path / "x.json"


def test_level_frames_are_cached_apart_and_the_default_keeps_its_cache_name(tmp_path):
    import argparse

    args = argparse.Namespace(cache=tmp_path, worlds=6, per_world=3, references=1, pairs=0, far=4,
                              robust=merge.ROBUST, max_tilt=merge.MAX_TILT_DEG)
    default = merge.cache_path(args, 519809)
    args.max_tilt = 0.0
    level = merge.cache_path(args, 519809)
    assert level != default
    # the name the default had before --max-tilt existed: caches drawn then are still read
    drawn = (merge.CACHE_VERSION, 519809, 6, 3, 1, 0, 4, merge.ROBUST)
    assert default.name == f"merge_pairs-{merge.hashlib.sha1(repr(drawn).encode()).hexdigest()[:12]}.npz"
    assert merge.tilt_bound("-0.0") == 0.0 and merge.tilt_bound("2.5") == 2.5
    for bad in ("-1", "31", "nan"):
        with pytest.raises(merge.argparse.ArgumentTypeError):
            merge.tilt_bound(bad)


def test_errors_split_tilt_and_the_mean_offset():
    import numpy as np

    from coopd.geometry import euler_to_matrix, rigid
    from coopd.grid import OccupancyGrid

    b = OccupancyGrid.empty((20, 20, 10), 0.1)
    b.cells[2:18, 2:18, 1] = 90
    truth = rigid(euler_to_matrix(0.0, 0.0, 0.7), [1.0, 2.0, 0.0])
    shifted = merge.errors(rigid(np.eye(3), [0.03, 0.04, -0.05]) @ truth, truth, b)
    assert shifted["tilt_err_deg"] == 0.0 and shifted["rot_err_deg"] == 0.0
    assert shifted["offset_h_m"] == 0.05 and shifted["offset_v_m"] == 0.05
    tilted = merge.errors(truth @ rigid(euler_to_matrix(np.radians(1.0), 0.0, 0.0)), truth, b)
    assert abs(tilted["tilt_err_deg"] - 1.0) < 1e-6 and abs(tilted["rot_err_deg"] - 1.0) < 1e-6
    rows = [{"method": "coopd", "set": "fresh", "variant": "base", "overlap": 0.5, "accepted": True,
             "correct": True, **e} for e in (shifted, tilted)]
    split = merge.error_split(rows)
    assert split["merges"] == 2 and split["tilt_err_deg"] == [0.0, 1.0]
    assert merge.error_split(rows[:0]) is None

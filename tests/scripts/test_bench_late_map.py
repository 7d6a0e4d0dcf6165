"""scripts/benchmarks/late_map.py: how a late map's result is judged against the flight's truth."""

import importlib.util
from pathlib import Path

import numpy as np

from coopd.geometry import rigid, rotation_z
from coopd.merging.pair import MergeResult

ROOT = Path(__file__).resolve().parents[2]
spec = importlib.util.spec_from_file_location("bench_late_map",
                                              ROOT / "scripts" / "benchmarks" / "late_map.py")
late_map = importlib.util.module_from_spec(spec)
spec.loader.exec_module(late_map)


def result(accepted, transform, reason="accepted"):
    return MergeResult(accepted, transform, 100, 1.0, 500, 0, 0.0, reason, 0.3)


def test_a_result_is_right_within_the_tolerances_wrong_beyond_and_refused_when_not_accepted():
    truth = rigid(rotation_z(np.radians(30.0)), [4.0, -2.0, 0.5])
    near = rigid(rotation_z(np.radians(31.0)), [4.1, -2.0, 0.5])
    mirror = rigid(rotation_z(np.radians(210.0)), [-6.0, 9.0, 0.5])
    assert late_map.judged(result(True, near), truth, 0.3, 3.0)["verdict"] == "right"
    wrong = late_map.judged(result(True, mirror), truth, 0.3, 3.0)
    assert wrong["verdict"] == "wrong" and abs(wrong["error_deg"] - 180.0) < 0.01
    refused = late_map.judged(result(False, near, "overlap too small: 0.1"), truth, 0.3, 3.0)
    assert refused["verdict"] == "refused" and refused["reason"] == "overlap too small: 0.1"
    assert late_map.judged(result(True, rigid(rotation_z(np.radians(34.0)), [4.0, -2.0, 0.5])), truth, 0.3,
                           3.0)["verdict"] == "wrong"

"""scripts/benchmarks/merge_stages.py: each kernel measured next to its peer, on a small world."""

import importlib.util
import json
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
spec = importlib.util.spec_from_file_location("bench_merge_stages", ROOT / "scripts" / "benchmarks" /
                                              "merge_stages.py")
merge_stages = importlib.util.module_from_spec(spec)
spec.loader.exec_module(merge_stages)


@pytest.mark.slow
@pytest.mark.cpu_bound
def test_the_kernels_agree_with_their_peers_and_report_ratios(tmp_path, monkeypatch):
    out = tmp_path / "merge_stages.json"
    monkeypatch.setattr(sys, "argv", ["merge_stages", "--world", "small_house", "--repeat", "1",
                                      "--out", str(out)])
    assert merge_stages.main() == 0
    report = json.loads(out.read_text())
    kernels = report["kernels"]
    assert kernels["preprocess (per map)"]["max_abs_difference"] < 1e-3  # of 255
    for name, row in kernels.items():
        assert row["coopd_cpu_s"] >= 0
        if name.startswith("nearest occupied"):
            assert row["same_distances"] and row["speedup"] > 0
    assert kernels["fast3d (per map)"]["keypoints"] > 0

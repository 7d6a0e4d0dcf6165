"""scripts/benchmarks/obstacles.py: the daemon's update agrees with the brute-force reference."""

import importlib.util
import json
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
spec = importlib.util.spec_from_file_location("bench_obstacles",
                                              ROOT / "scripts" / "benchmarks" / "obstacles.py")
obstacles = importlib.util.module_from_spec(spec)
spec.loader.exec_module(obstacles)


def test_every_update_agrees_with_the_reference_and_the_report_has_the_ratio(tmp_path):
    out = tmp_path / "obstacles.json"
    assert obstacles.main(["--size", "3.6M", "--positions", "4", "--repeat", "1", "--out", str(out)]) == 0
    report = json.loads(out.read_text())
    assert report["agree"] == 4 and len(report["rows"]) == 4
    assert report["speedup_median"] > 0 and report["update_ms"]["max"] >= report["update_ms"]["median"]

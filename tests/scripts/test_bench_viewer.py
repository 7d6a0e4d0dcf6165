"""scripts/benchmarks/viewer.py: a real client counts the bytes; incremental sends less than full."""

import importlib.util
import json
from pathlib import Path

import pytest

pytest.importorskip("foxglove")
ROOT = Path(__file__).resolve().parents[2]
spec = importlib.util.spec_from_file_location("bench_viewer", ROOT / "scripts" / "benchmarks" / "viewer.py")
viewer = importlib.util.module_from_spec(spec)
spec.loader.exec_module(viewer)


def test_incremental_sends_fewer_bricks_and_bytes_than_full(tmp_path):
    out = tmp_path / "viewer.json"
    assert viewer.main(["--size", "250k", "--ticks", "5", "--out", str(out)]) == 0
    report = json.loads(out.read_text())
    inc, full = report["incremental"], report["full"]
    assert inc["bytes_first_tick"] == full["bytes_first_tick"] > 0  # the same start map
    assert inc["bricks_non_empty_at_end"] == full["bricks_non_empty_at_end"]
    assert inc["bricks_sent_per_tick"]["mean"] < full["bricks_sent_per_tick"]["mean"]
    assert inc["bytes_total"] < full["bytes_total"] and report["full_over_incremental"] > 1

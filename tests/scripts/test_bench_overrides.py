"""The benches' KEY=VALUE,... parser (scripts/benchmarks/_overrides.py), shared by --set and --mapper."""

import importlib.util
from pathlib import Path

import pytest

from coopd.mapping import MapperConfig
from coopd.merging.params import coopd_params

ROOT = Path(__file__).resolve().parents[2]
spec = importlib.util.spec_from_file_location("bench_overrides",
                                              ROOT / "scripts" / "benchmarks" / "_overrides.py")
ov = importlib.util.module_from_spec(spec)
spec.loader.exec_module(ov)


def test_values_take_the_type_of_the_fields_default():
    assert ov.overrides("graze_deg=0,traversal=exact,gap_fill=no,miss_decrement=5", MapperConfig()) == {
        "graze_deg": 0.0, "traversal": "exact", "gap_fill": False, "miss_decrement": 5}
    assert ov.overrides("min_score=0.96,refine=true", coopd_params()) == {"min_score": 0.96, "refine": True}
    assert ov.overrides("", MapperConfig()) == {}


@pytest.mark.parametrize("text", ["nonsense=1", "miss_decrement=five", "gap_fill=flase", "graze_deg",
                                  "resolution=0.2"])
def test_unknown_fixed_or_mistyped_settings_are_refused(text):
    with pytest.raises(ValueError):
        ov.overrides(text, MapperConfig(), fixed=("resolution",))

"""scripts/benchmarks/share.py --delta over Zenoh: a short recording replayed between two services on
loopback counts the map bytes that cross the link (shared memory off: a map is not passed by reference)."""

import importlib.util
import shutil
import sys
from pathlib import Path

import pytest

pytest.importorskip("zenoh")
ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "tests" / "sharing"))  # its helpers import each other by bare name
from sharing_support import growing_maps  # noqa: E402

spec = importlib.util.spec_from_file_location("bench_share", ROOT / "scripts" / "benchmarks" / "share.py")
share = importlib.util.module_from_spec(spec)
spec.loader.exec_module(share)


@pytest.mark.skipif(shutil.which("ss") is None, reason="needs ss (iproute2)")
def test_zenoh_replay_counts_the_bytes_on_the_link_full_and_as_deltas():
    recording = [(float(v), message) for _, v, message in growing_maps(12)]
    full_bytes = sum(len(m) for _, m in recording)
    runs = {deltas: share.replay(recording, share.ZenohPair(1, deltas, 8, idle_sample_s=0.5), 4.0)
            for deltas in (False, True)}
    full, delta = runs[False], runs[True]
    assert full["identical"] and delta["identical"]
    assert (full["maps_sent"], full["deltas_sent"]) == (12, 0) and delta["deltas_sent"] == 11
    assert full["message_bytes"] >= full_bytes  # the envelopes: each map and its 3-byte header
    assert full["message_bytes"] <= full["wire_bytes"] < full["message_bytes"] * 1.1  # plus Zenoh's framing
    assert delta["message_bytes"] <= delta["wire_bytes"] < full["wire_bytes"] / 2
    assert full["idle_link_bytes_per_min"] < 10_000  # keep-alives, a few bytes every 2.5 s

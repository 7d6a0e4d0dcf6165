"""`coopctl map merge`: offline merging of .cmap files, with the JSON report the issue names."""

import json

import numpy as np
import pytest

from coopd.cli.coopctl import main
from coopd.geometry import rotation_angle_deg
from coopd.io import load_cmap, save_cmap
from coopd.sharing.wire import MapMeta
from firmware_sim.benchset import make_pair, make_world


@pytest.fixture(scope="module")
def pair():
    return make_pair(make_world(0), 101, 3.0)


def test_merge_two_files_reports_the_transform(tmp_path, capsys, pair):
    a, b, out = tmp_path / "a.cmap", tmp_path / "b.cmap", tmp_path / "global.cmap"
    save_cmap(a, pair.a, MapMeta(1, 5, 0.0))
    save_cmap(b, pair.b, MapMeta(2, 7, 0.0))
    assert main(["map", "merge", str(a), str(b), "-o", str(out), "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    entry = report["maps"][0]
    assert set(entry) >= {"accepted", "transform", "inliers", "score", "seconds"}
    assert entry["accepted"] is True
    t = np.array(entry["transform"])
    assert t.shape == (4, 4)
    assert np.linalg.norm(t[:3, 3] - pair.a_from_b[:3, 3]) < 0.2
    assert rotation_angle_deg(t[:3, :3].T @ pair.a_from_b[:3, :3]) < 2.0
    merged, meta = load_cmap(out)
    assert meta.vehicle_id == 1
    assert merged.counts().known > pair.a.counts().known


def test_unmergeable_maps_exit_3_and_say_why(tmp_path, capsys):
    far = make_pair(make_world(0), 905, 16.0, box_size_m=6.0)
    a, b, out = tmp_path / "a.cmap", tmp_path / "b.cmap", tmp_path / "g.cmap"
    save_cmap(a, far.a, MapMeta(1, 1, 0.0))
    save_cmap(b, far.b, MapMeta(2, 1, 0.0))
    assert main(["map", "merge", str(a), str(b), "-o", str(out)]) == 3
    text = capsys.readouterr().out
    assert "not merged" in text


def test_merge_needs_two_files(tmp_path, capsys):
    a = tmp_path / "a.cmap"
    save_cmap(a, make_pair(make_world(0), 101, 3.0).a, MapMeta(1, 1, 0.0))
    assert main(["map", "merge", str(a), "-o", str(tmp_path / "o.cmap")]) == 1
    assert "at least two" in capsys.readouterr().err

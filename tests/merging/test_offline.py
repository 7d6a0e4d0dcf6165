import json

import numpy as np

from coopd.grid import OccupancyGrid
from coopd.merging.offline import merge_files


def _save(grid, path):
    np.savez(path, cells=grid.cells, offset=grid.offset, resolution=grid.resolution)


def _load(path):
    with np.load(path) as z:
        return OccupancyGrid(z["cells"], float(z["resolution"]), z["offset"])


def test_merge_files_reports_every_input_after_the_first(tmp_path, near_pair, far_pair):
    paths = []
    for name, g in [("a", near_pair.a), ("b", near_pair.b), ("far", far_pair.b)]:
        p = tmp_path / f"{name}.npz"
        _save(g, p)
        paths.append(p)
    out = tmp_path / "out.npz"
    report = merge_files(paths, out, _load, _save)
    json.dumps(report)  # JSON-ready
    assert len(report["maps"]) == 2
    b, far = report["maps"]
    assert b["accepted"] and not far["accepted"]
    t = np.array(b["transform"])
    assert t.shape == (4, 4) and np.allclose(t[3], [0, 0, 0, 1])
    assert np.linalg.norm(t[:3, 3] - near_pair.a_from_b[:3, 3]) < 0.2
    for entry in report["maps"]:
        assert {"accepted", "transform", "inliers", "score", "seconds"} <= set(entry)
    merged = _load(out)
    assert merged.counts().known > near_pair.a.counts().known

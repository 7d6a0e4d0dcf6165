"""`coopctl map info|convert` on real files, through main() as the entry point calls it."""

import json
import os

import numpy as np
import pytest
from PIL import Image

from coopd.cli.coopctl import main
from coopd.grid import OccupancyGrid
from coopd.io import load_cmap, save_cmap
from coopd.sharing.wire import MapMeta, encode_thesis_map
from tests.sharing.realistic_maps import building_map


@pytest.fixture
def cmap(tmp_path):
    grid = OccupancyGrid(building_map((40, 30, 12), explored=0.5, seed=4), 0.1, (-20, -15, -2))
    path = tmp_path / "uav1.cmap"
    save_cmap(path, grid, MapMeta(vehicle_id=1, version=5, stamp=100.0))
    return path, grid


def test_info_reports_the_map(cmap, capsys):
    path, grid = cmap
    assert main(["map", "info", str(path), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    counts = grid.counts()
    assert info["shape"] == [40, 30, 12] and info["resolution_m"] == 0.1
    assert info["origin_cells"] == [-20, -15, -2]
    assert info["origin_m"] == pytest.approx([-2.0, -1.5, -0.2])
    assert info["known"] == counts.known and info["occupied"] == counts.occupied
    assert info["compression_ratio"] == pytest.approx(grid.size / path.stat().st_size)
    assert main(["map", "info", str(path)]) == 0
    assert "compression" in capsys.readouterr().out


def test_info_reads_thesis_messages(tmp_path, capsys):
    path = tmp_path / "thesis.cmap"
    path.write_bytes(encode_thesis_map(OccupancyGrid(np.zeros((3, 3, 3), np.int8), 0.1), 8))
    assert main(["map", "info", str(path), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["message_type"] == 0 and info["vehicle_id"] == 8 and info["free"] == 27


@pytest.mark.parametrize("fmt", ["ply", "bt", "cmap"])
def test_convert_writes_files(cmap, fmt, capsys):
    path, grid = cmap
    assert main(["map", "convert", str(path), "--to", fmt]) == 0
    out = capsys.readouterr().out.split("wrote ")[1].split(" (")[0]
    data = open(out, "rb").read()
    assert data.startswith({"ply": b"ply\n", "bt": b"# Octomap OcTree binary file", "cmap": b"\x01\x01"}[fmt])
    if fmt == "cmap":
        back, _ = load_cmap(out)
        assert np.array_equal(back.cells, grid.cells)


def test_convert_png_top_and_slice(cmap, tmp_path, capsys):
    path, grid = cmap
    assert main(["map", "convert", str(path), "--to", "png", "-o", str(tmp_path / "top.png"), "--json"]) == 0
    title = "coopd map of vehicle 1, 1970-01-01 00:01:40 UTC, 0.1 m/cell"
    assert json.loads(capsys.readouterr().out)["title"] == title
    z_args = ["--z", "0.3", "-o", str(tmp_path / "z.png")]
    assert main(["map", "convert", str(path), "--to", "png", *z_args]) == 0
    top, z = Image.open(tmp_path / "top.png"), Image.open(tmp_path / "z.png")
    assert top.info["Title"] == title and z.info["Title"].startswith("coopd map slice z = 0.3 m")
    # the top view adds the title above, the metre axes and the scale bar around the same map
    assert top.size[0] > z.size[0] and top.size[1] > z.size[1]


def test_errors_are_one_line_and_exit_1(tmp_path, capsys):
    bad = tmp_path / "bad.cmap"
    bad.write_bytes(b"\x05garbage")
    assert main(["map", "info", str(bad)]) == 1
    assert main(["map", "info", str(tmp_path / "missing.cmap")]) == 1
    err = capsys.readouterr().err
    assert err.count("coopctl: error:") == 2 and "unknown message type 5" in err


def test_z_only_with_png(cmap):
    path, _ = cmap
    assert main(["map", "convert", str(path), "--to", "ply", "--z", "1"]) == 2  # usage


def test_runs_as_a_program_without_a_daemon(cmap):
    import subprocess
    import sys
    from pathlib import Path

    path, _ = cmap
    root = Path(__file__).resolve().parents[2]
    done = subprocess.run([sys.executable, "-m", "coopd.cli.coopctl", "map", "info", str(path)], cwd=root,
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert "40 x 30 x 12" in done.stdout


def test_errors_name_the_file(tmp_path, capsys):
    bad, empty = tmp_path / "bad.cmap", tmp_path / "empty.cmap"
    bad.write_bytes(b"\x05garbage")
    empty.write_bytes(b"")
    for path in (bad, empty, tmp_path / "missing.cmap", tmp_path):
        assert main(["map", "info", str(path)]) == 1
        assert capsys.readouterr().err.startswith(f"coopctl: error: {path}: "), path
        assert main(["map", "convert", str(path), "--to", "ply"]) == 1
        assert capsys.readouterr().err.startswith(f"coopctl: error: {path}: "), path
    assert main(["map", "info", str(bad), "--json"]) == 1
    expected = {"error": f"{bad}: unknown message type 5", "code": "failed", "exit": 1}
    assert json.loads(capsys.readouterr().out) == expected


def test_convert_json_and_the_umask(cmap, tmp_path, capsys):
    path, grid = cmap
    out = tmp_path / "out.bt"
    old = os.umask(0o002)
    try:
        assert main(["map", "convert", str(path), "--to", "bt", "-o", str(out), "--json"]) == 0
    finally:
        os.umask(old)
    assert json.loads(capsys.readouterr().out) == {"source": str(path), "file": str(out), "format": "bt",
                                                   "bytes": out.stat().st_size}
    assert out.stat().st_mode & 0o777 == 0o664

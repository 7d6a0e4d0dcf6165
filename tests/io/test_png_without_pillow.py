"""The drone install has no Pillow: maps still load and export to the other formats, and a PNG
export is one clear error naming the extra that brings Pillow, with nothing written."""

import os
import subprocess
import sys
from pathlib import Path

import pytest

from coopd.grid import OccupancyGrid
from coopd.io import export_png_slice, export_png_top
from coopd.io.png import PillowMissing

ROOT = Path(__file__).resolve().parents[2]


def small_map() -> OccupancyGrid:
    grid = OccupancyGrid.empty((8, 8, 4), 0.1)
    grid.cells[2:6, 2:6, 1] = 90
    return grid


@pytest.mark.parametrize("export", [export_png_top, lambda g, p: export_png_slice(g, p, 0.15)])
def test_png_export_names_the_tools_extra(monkeypatch, tmp_path, export):
    monkeypatch.setitem(sys.modules, "PIL", None)  # import PIL now raises ImportError
    out = tmp_path / "map.png"
    with pytest.raises(PillowMissing, match=r"coopd\[tools\]"):
        export(small_map(), out)
    assert not out.exists()


def test_coopctl_says_which_extra_brings_pillow_without_a_traceback(monkeypatch, tmp_path, capsys):
    from coopd.cli.coopctl import main as coopctl
    from coopd.io import save_cmap
    from coopd.sharing.wire import MapMeta

    save_cmap(tmp_path / "m.cmap", small_map(), MapMeta(1, 1))
    monkeypatch.setitem(sys.modules, "PIL", None)
    assert coopctl(["map", "convert", str(tmp_path / "m.cmap"), "--to", "png", "--json"]) == 1
    out = capsys.readouterr()
    assert '"missing_extra": "tools"' in out.out and "coopd[tools]" in out.out and "Traceback" not in out.err


def test_coopd_io_imports_and_exports_ply_without_pillow(tmp_path):
    code = ("import sys; sys.modules['PIL'] = None\n"
            "import numpy as np\n"
            "from coopd.grid import OccupancyGrid\n"
            "from coopd.io import export_ply\n"
            "g = OccupancyGrid.empty((4, 4, 4), 0.1); g.cells[1, 1, 1] = 90\n"
            f"print(export_ply(g, {str(tmp_path / 'map.ply')!r}))\n")
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=300)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "1" and (tmp_path / "map.ply").stat().st_size > 0


def test_with_pillow_the_export_still_draws(tmp_path):
    export_png_top(small_map(), tmp_path / "map.png")
    assert (tmp_path / "map.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"

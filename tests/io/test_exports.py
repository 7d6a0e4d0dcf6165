"""Exports people can open: PLY, PNG (top view, slices), OctoMap .bt read back by OctoMap."""

import numpy as np
import pytest
from PIL import Image

from coopd.grid import OccupancyGrid
from coopd.io import export_bt, export_ply, export_png_slice, export_png_top
from coopd.io.bt import bt_bytes
from coopd.io.png import COLOURS, FREE, INACCESSIBLE, OCCUPIED, UNKNOWN, scale_for
from tests.sharing.realistic_maps import building_map


def sample_grid() -> OccupancyGrid:
    cells = np.full((12, 10, 6), -1, np.int8)
    cells[2, 3, :] = 0            # free column
    cells[5, 5, 2] = 100          # occupied in layer 2 only
    cells[5, 5, 1] = 0
    cells[7, 1, 4] = -2           # inaccessible
    cells[9, 8, 0:3] = [10, 75, 50]
    return OccupancyGrid(cells, 0.2, (-6, -5, -1))


def read_ply(path):
    data = path.read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    header = data[:end].decode()
    n = int(header.split("element vertex ")[1].split()[0])
    dt = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("occupancy", "u1")])
    assert "format binary_little_endian 1.0" in header
    return np.frombuffer(data[end:], dtype=dt, count=n), len(data) - end - n * dt.itemsize


def test_ply_holds_the_occupied_cell_centres(tmp_path):
    grid = sample_grid()
    assert export_ply(grid, tmp_path / "m.ply") == 3
    vertices, trailing = read_ply(tmp_path / "m.ply")
    assert trailing == 0
    got = sorted(zip(np.round(vertices["x"] / 0.2).astype(int), np.round(vertices["y"] / 0.2).astype(int),
                     np.round(vertices["z"] / 0.2).astype(int), vertices["occupancy"], strict=True))
    assert got == [(-1, 0, 1, 100), (3, 3, 0, 75), (3, 3, 1, 50)]


def pixel(image, grid, x, y, map_left_top=(0, 0)):
    s = scale_for(grid.shape[:2])
    left, top = map_left_top
    return image.getpixel((left + x * s + s // 2, top + (grid.shape[1] - 1 - y) * s + s // 2))


def test_png_top_view_size_and_colours(tmp_path):
    grid = sample_grid()
    layout = export_png_top(grid, tmp_path / "top.png")
    image = Image.open(tmp_path / "top.png").convert("RGB")
    s = scale_for(grid.shape[:2])
    left, top, right, bottom = layout.map_box
    assert image.size == layout.size
    assert (right - left, bottom - top) == (grid.shape[0] * s, grid.shape[1] * s)
    expect = {(2, 3): FREE, (5, 5): OCCUPIED, (7, 1): INACCESSIBLE, (9, 8): OCCUPIED, (0, 0): UNKNOWN}
    for (x, y), cls in expect.items():
        assert pixel(image, grid, x, y, (left, top)) == tuple(COLOURS[cls]), (x, y)


def test_png_slice_picks_the_layer(tmp_path):
    grid = sample_grid()
    export_png_slice(grid, tmp_path / "s.png", z_m=0.0)   # key 0 -> array layer 1
    image = Image.open(tmp_path / "s.png").convert("RGB")
    assert pixel(image, grid, 5, 5) == tuple(COLOURS[FREE])
    assert pixel(image, grid, 9, 8) == tuple(COLOURS[OCCUPIED])
    export_png_slice(grid, tmp_path / "s2.png", z_m=0.21)  # key 1 -> layer 2
    image = Image.open(tmp_path / "s2.png").convert("RGB")
    assert pixel(image, grid, 5, 5) == tuple(COLOURS[OCCUPIED])
    with pytest.raises(ValueError, match="outside the map"):
        export_png_slice(grid, tmp_path / "bad.png", z_m=5.0)


def _octomap_labels(tree, grid):
    keys = np.argwhere(np.ones(grid.shape, bool)) + grid.offset
    return tree.getLabels((keys + 0.5) * grid.resolution).reshape(grid.shape)


@pytest.mark.parametrize("seed", [0, 1])
def test_bt_read_back_by_octomap(tmp_path, seed):
    octomap = pytest.importorskip("octomap")
    grid = OccupancyGrid(building_map((48, 40, 16), explored=0.6, seed=seed), 0.1, (-24, -20, -4))
    export_bt(grid, tmp_path / "m.bt")
    tree = octomap.OcTree(0.1)
    assert tree.readBinary(str(tmp_path / "m.bt"))
    labels = _octomap_labels(tree, grid)
    cells = grid.cells
    assert np.array_equal(labels == 1, cells >= 50)
    assert np.array_equal(labels == 0, (cells >= 0) & (cells < 50))
    assert np.array_equal(labels == -1, cells < 0)


def test_bt_bytes_equal_octomaps_own_writer():
    octomap = pytest.importorskip("octomap")
    grid = OccupancyGrid(building_map((24, 20, 10), explored=0.7, seed=5), 0.1, (0, 0, 0))
    tree = octomap.OcTree(0.1)
    for k in np.argwhere(grid.cells >= 0):
        tree.updateNode((k + 0.5) * 0.1, bool(grid.cells[tuple(k)] >= 50))
    ref = tree.writeBinary()
    mine = bt_bytes(grid)
    assert mine.split(b"data\n", 1)[1] == ref.split(b"data\n", 1)[1]
    assert mine.split(b"size ")[1].split(b"\n")[0] == ref.split(b"size ")[1].split(b"\n")[0]


def test_bt_of_an_unknown_map_is_an_empty_tree(tmp_path):
    octomap = pytest.importorskip("octomap")
    export_bt(OccupancyGrid.empty((4, 4, 4)), tmp_path / "e.bt")
    tree = octomap.OcTree(0.1)
    assert tree.readBinary(str(tmp_path / "e.bt"))
    assert tree.size() == 0

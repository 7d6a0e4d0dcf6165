""".cmap files: the wire bytes on disk, written atomically, read back identical."""

import os

import numpy as np
import pytest

from coopd.grid import OccupancyGrid
from coopd.io import load_cmap, save_cmap
from coopd.io.atomic import PRIVATE, write_atomic
from coopd.sharing.wire import DecodeLimits, MapMeta, WireError, encode_map
from tests.sharing.realistic_maps import building_map


def test_cmap_round_trip_is_identical(tmp_path):
    grid = OccupancyGrid(building_map((50, 40, 20), explored=0.5, seed=2), 0.1, (-25, -20, -3))
    meta = MapMeta(vehicle_id=4, version=17, stamp=1_763_770_000.5)
    path = tmp_path / "map.cmap"
    n = save_cmap(path, grid, meta)
    assert path.stat().st_size == n
    assert path.read_bytes() == encode_map(grid, meta)
    back, back_meta = load_cmap(path)
    assert back_meta == meta and back.resolution == grid.resolution
    assert np.array_equal(back.offset, grid.offset) and np.array_equal(back.cells, grid.cells)


def test_atomic_write_leaves_no_temp_and_keeps_old_file_on_failure(tmp_path, monkeypatch):
    path = tmp_path / "a.cmap"
    write_atomic(path, b"old")

    def boom(*_):
        raise OSError("disk full")

    monkeypatch.setattr(os, "fsync", boom)
    with pytest.raises(OSError, match="disk full"):
        write_atomic(path, b"new")
    assert path.read_bytes() == b"old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.cmap"]


def test_load_refuses_oversized_and_corrupt_files(tmp_path):
    grid = OccupancyGrid(np.zeros((4, 4, 4), np.int8), 0.1)
    path = tmp_path / "m.cmap"
    n = save_cmap(path, grid, MapMeta(1))
    with pytest.raises(WireError, match="exceeds the limit"):
        load_cmap(path, DecodeLimits(max_bytes=n - 1))
    data = bytearray(path.read_bytes())
    data[-1] ^= 0x40
    path.write_bytes(bytes(data))
    with pytest.raises(WireError, match="m.cmap"):
        load_cmap(path)


def test_load_refuses_non_regular_files(tmp_path):
    with pytest.raises(WireError, match="not a regular file"):
        load_cmap("/dev/zero")


@pytest.fixture
def umask():
    """Set the process umask for one test (returns a setter); the old one is restored."""
    old = os.umask(0o022)
    yield os.umask
    os.umask(old)


@pytest.mark.parametrize("mask, mode", [(0o022, 0o644), (0o027, 0o640), (0o077, 0o600), (0o002, 0o664)])
def test_written_files_follow_the_umask(tmp_path, umask, mask, mode):
    umask(mask)
    path = tmp_path / "a.cmap"
    write_atomic(path, b"map")
    assert os.stat(path).st_mode & 0o777 == mode
    path.chmod(0o600)  # replacing a file gives the new file the umask's mode too
    write_atomic(path, b"map 2")
    assert os.stat(path).st_mode & 0o777 == mode and path.read_bytes() == b"map 2"


def test_private_files_are_0600_whatever_the_umask(tmp_path, umask):
    umask(0)
    write_atomic(tmp_path / "state", b"secret", PRIVATE)
    assert os.stat(tmp_path / "state").st_mode & 0o777 == 0o600

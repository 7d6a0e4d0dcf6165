"""OctoMap .bt / .ot files read into coopd maps: round trips with coopd's own export and with OctoMap,
hostile files refused before allocating, and an OctoMap of one drone merged with coopd's map of
another."""

import json

import numpy as np
import pytest

from coopd.cli.coopctl import main as coopctl
from coopd.geometry import apply, invert, rigid, rotation_angle_deg, rotation_z
from coopd.grid import OccupancyGrid
from coopd.io import load_map, save_cmap
from coopd.io.bt import bt_bytes, read_octomap
from coopd.mapping import Intrinsics, Mapper, MapperConfig
from coopd.merging import merge_pair
from coopd.sharing.wire import MapMeta
from tests.synthetic_scenes import render_depth, room_scene, survey_poses

octomap = pytest.importorskip("octomap")
# The module's tests share two_drones (about 20 s to map): under pytest-xdist they run on one worker,
# which builds it once, instead of each worker that takes one of them building it again.
pytestmark = pytest.mark.xdist_group("octomap-two-drones")

RES = 0.1


def _classes(grid: OccupancyGrid) -> dict:
    """{cell key: occupied?} of the known cells."""
    keys = np.argwhere(grid.cells >= 0) + grid.offset
    occupied = grid.cells[grid.cells >= 0] >= 50
    return dict(zip(map(tuple, keys.tolist()), occupied.tolist(), strict=True))


def _octomap_tree(seed: int = 0) -> "octomap.OcTree":
    tree = octomap.OcTree(RES)
    rng = np.random.default_rng(seed)
    tree.insertPointCloud(rng.uniform(-2.0, 2.0, (3000, 3)), np.zeros(3), maxrange=-1.0)
    return tree


def test_coopd_export_reads_back_cell_for_cell(two_drones):
    grid = two_drones[0]
    back = read_octomap(bt_bytes(grid), 10**8)
    assert back.resolution == grid.resolution
    assert _classes(back) == _classes(grid)


@pytest.mark.parametrize("suffix", ["bt", "ot"])
def test_every_octomap_leaf_lands_on_its_cells(tmp_path, suffix):
    """Each leaf OctoMap itself reports (centre, depth, occupancy) covers the cells it stands for:
    OctoMap key k is coopd cell k - 32768, so a leaf of s cells per axis centred at c starts at cell
    c / res - s / 2."""
    tree = _octomap_tree()
    path = tmp_path / f"tree.{suffix}"
    (tree.writeBinary if suffix == "bt" else tree.write)(str(path).encode())
    grid, meta = load_map(path)
    assert meta.vehicle_id == 0 and grid.resolution == RES
    checked = 0
    for leaf in tree.begin_leafs():
        size = 2 ** (16 - leaf.getDepth())
        corner = np.rint(np.asarray(leaf.getCoordinate()) / RES - size / 2).astype(int)
        cube = grid.cells[tuple(slice(c - o, c - o + size) for c, o in zip(corner, grid.offset, strict=True))]
        assert cube.shape == (size,) * 3
        if suffix == "bt":
            assert ((cube >= 50) == bool(tree.isNodeOccupied(leaf))).all()
        else:
            assert (cube == round(100 * leaf.getOccupancy())).all()
        checked += 1
    assert checked > 1000
    known = (grid.cells >= 0).sum()
    assert known == sum((2 ** (16 - leaf.getDepth())) ** 3 for leaf in tree.begin_leafs())


def _tree_bytes(tmp_path, suffix="bt") -> bytes:
    path = tmp_path / f"t.{suffix}"
    (_octomap_tree().writeBinary if suffix == "bt" else _octomap_tree().write)(str(path).encode())
    return path.read_bytes()


@pytest.mark.parametrize("suffix", ["bt", "ot"])
def test_hostile_files_are_refused_with_a_reason(tmp_path, suffix):
    data = _tree_bytes(tmp_path, suffix)
    head_end = data.index(b"data\n") + 5
    cases = {  # the broken file, and what the refusal must say
        "truncated": (data[:-3], "truncated"),
        "trailing": (data + b"\x00\x00", "after the OctoMap tree"),
        "announces": (data.replace(b"\nsize ", b"\nsize 1", 1), "announces"),
        "no data line": (data[: head_end - 5], "without a 'data' line"),
        "not a number": (data.replace(b"\nres ", b"\nres x", 1), "not numbers"),
        "type": (data.replace(b"id OcTree", b"id CountingOcTree", 1), "CountingOcTree"),
    }
    for bad, why in cases.values():
        with pytest.raises(ValueError, match=why):
            read_octomap(bad, 10**8)
    rng = np.random.default_rng(1)
    for _ in range(300):  # flipped bytes in the tree: a clear ValueError or a grid, nothing else
        bad = bytearray(data)
        for pos in rng.integers(head_end, len(bad), 3):
            bad[pos] ^= int(rng.integers(1, 256))
        try:
            read_octomap(bytes(bad), 10**7)
        except ValueError:
            pass


def test_a_tree_spanning_more_cells_than_allowed_is_refused_before_allocating():
    """One occupied leaf right under the root stands for 32768^3 cells."""
    header = b"# Octomap OcTree binary file\nid OcTree\nsize 2\nres 0.1\ndata\n"
    with pytest.raises(ValueError, match="more than the limit"):
        read_octomap(header + bytes([0b10, 0]), 10**8)
    deep = b"# Octomap OcTree binary file\nid OcTree\nsize 17\nres 0.1\ndata\n" + bytes([3, 0]) * 16 + b""
    with pytest.raises(ValueError):
        read_octomap(deep, 10**8)


def _frames_map_and_octomap(scene, b_from_world):
    """coopd maps the room from survey poses in the world frame (drone A); drone B's frames, from
    other stations and expressed in B's frame, go into an OctoMap as point clouds with their origins."""
    intr = Intrinsics.from_fov(160, 120, 87.0)
    sx, sy = intr.ray_slopes()
    mapper = Mapper(MapperConfig(resolution=RES, max_range=6.0))
    tree = octomap.OcTree(RES)
    for pose in survey_poses(4, 12, radius=1.0):
        mapper.integrate(render_depth(scene, intr, pose), intr, pose)
    for pose in survey_poses(4, 12, height=1.5, radius=1.6):
        depth = render_depth(scene, intr, pose).astype(np.float64)  # metres
        pts = np.stack([sx[None, :] * depth, sy[:, None] * depth, depth], -1).reshape(-1, 3)
        pts = pts[(depth.reshape(-1) > 0.2) & (depth.reshape(-1) <= 6.0)]
        world = pts @ pose.rotation().T + pose.position
        origin = apply(b_from_world, pose.position[None])[0]
        tree.insertPointCloud(apply(b_from_world, world), origin, maxrange=6.0)
    mapper.close()
    return mapper.grid, tree


B_FROM_WORLD = rigid(rotation_z(np.radians(120.0)), [1.3, -0.7, 0.0])


@pytest.fixture(scope="module")
def two_drones():
    """(coopd's map of drone A, drone B's OctoMap) of one room."""
    return _frames_map_and_octomap(room_scene(3), B_FROM_WORLD)


def test_an_octomap_of_one_drone_merges_with_coopds_map_of_another(tmp_path, two_drones):
    a_grid, tree = two_drones
    b_from_world = B_FROM_WORLD
    tree.writeBinary(str(tmp_path / "b.bt").encode())
    b_grid, _ = load_map(tmp_path / "b.bt")
    # the import keeps OctoMap's keys: its cell centres sit half a cell below OctoMap's coordinates
    truth = invert(b_from_world) @ rigid(translation=np.full(3, RES / 2))
    result = merge_pair(a_grid, b_grid)
    assert result.accepted, result.reason
    points = (np.argwhere(b_grid.cells >= 50) + b_grid.offset) * RES
    displacement = np.linalg.norm(apply(result.transform, points) - apply(truth, points), axis=1)
    print(f"OctoMap of drone B merged: {rotation_angle_deg(result.transform[:3, :3].T @ truth[:3, :3]):.2f} "
          f"deg, mean displacement {displacement.mean():.3f} m, max {displacement.max():.3f} m")
    assert rotation_angle_deg(result.transform[:3, :3].T @ truth[:3, :3]) < 2.0
    assert displacement.mean() <= 0.1


def test_coopctl_converts_and_merges_octomap_files(tmp_path, capsys, two_drones):
    _octomap_tree().writeBinary(str(tmp_path / "t.bt").encode())
    assert coopctl(["map", "convert", str(tmp_path / "t.bt"), "--to", "cmap",
                    "-o", str(tmp_path / "t.cmap")]) == 0
    grid, _ = load_map(tmp_path / "t.cmap")
    assert _classes(grid) == _classes(load_map(tmp_path / "t.bt")[0])
    capsys.readouterr()
    assert coopctl(["map", "info", str(tmp_path / "t.bt"), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["format"] == "octomap .bt (OcTree)" and info["vehicle_id"] is None and info["occupied"] > 0
    save_cmap(tmp_path / "a.cmap", two_drones[0], MapMeta(3, 1))
    two_drones[1].writeBinary(str(tmp_path / "b.bt").encode())
    assert coopctl(["map", "merge", str(tmp_path / "a.cmap"), str(tmp_path / "b.bt"), "-o",
                    str(tmp_path / "g.cmap"), "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["maps"][0]["accepted"]

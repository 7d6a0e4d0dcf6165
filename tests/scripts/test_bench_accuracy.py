"""scripts/benchmarks/accuracy.py's replay: camera poses along a trajectory, OctoMap's tree read as a
grid, and coopd and OctoMap fed the same frames of a short flight, scored with the surface metric."""

import importlib.util
from pathlib import Path

import numpy as np
import pytest

from coopd.mapping import MapperConfig
from firmware_sim import accuracy as acc
from firmware_sim.camera import CameraConfig
from firmware_sim.worlds import build_world

ROOT = Path(__file__).resolve().parents[2]
spec = importlib.util.spec_from_file_location("bench_accuracy",
                                              ROOT / "scripts" / "benchmarks" / "accuracy.py")
bench = importlib.util.module_from_spec(spec)
spec.loader.exec_module(bench)


def straight_flight(start, yaw, speed=0.5, seconds=6.0, height=1.0):
    """Rows (t, x, y, z, qw, qx, qy, qz) at 25 Hz of a level flight along a heading."""
    t = np.arange(0.0, seconds, 0.04)
    d = np.array([np.cos(yaw), np.sin(yaw)])
    xy = np.asarray(start) + speed * t[:, None] * d
    return np.c_[t, xy, np.full_like(t, height), np.full_like(t, np.cos(yaw / 2)), np.zeros_like(t),
                 np.zeros_like(t), np.full_like(t, np.sin(yaw / 2))]


def test_camera_poses_interpolate_the_trajectory():
    traj = straight_flight((1.0, 2.0), yaw=np.pi / 2)
    poses = bench.camera_poses(traj, CameraConfig(), 0.3)
    assert len(poses) == 20
    origin, rot = poses[3]
    assert np.allclose(origin, [1.0, 2.0 + 0.5 * 0.9, 1.0])
    assert np.allclose(rot[:, 2], [0.0, 1.0, 0.0], atol=1e-9)    # optical z looks along the heading


def test_flight_span_leaves_out_the_time_on_the_ground():
    flight = straight_flight((0.0, 0.0), 0.0, seconds=4.0)
    flight[:, 0] += 10.0
    parked = np.repeat(flight[:1], 100, axis=0)
    parked[:, 0] = np.arange(100) * 0.04 + 6.0
    landed = np.repeat(flight[-1:], 100, axis=0)
    landed[:, 0] = np.arange(100) * 0.04 + 14.0
    span = bench.flight_span(np.vstack([parked, flight, landed]))
    assert span[0, 0] == pytest.approx(10.0 + 0.12 - 1.0)
    assert span[-1, 0] == pytest.approx(14.0 - 0.12 + 1.0, abs=0.05)


def test_octree_grid_holds_octomap_cells_where_octomap_has_them():
    octomap = pytest.importorskip("octomap")
    tree = octomap.OcTree(0.1)
    rng = np.random.default_rng(0)
    wall = np.c_[np.full(5000, 3.02), rng.uniform(-1, 1, 5000), rng.uniform(-0.5, 0.5, 5000)]
    tree.insertPointCloud(wall, np.zeros(3), maxrange=5.0)
    grid, world_from_map = bench.octree_grid(tree, 0.1)
    centres = acc.occupied_centres(grid, acc.transform_points(world_from_map))
    assert len(centres) > 0 and np.allclose(centres[:, 0], 3.05)
    for p in centres[::50]:
        assert tree.isNodeOccupied(tree.search(p))
    free = np.array([[1.0, 0.0, 0.0], [2.5, 0.3, 0.1]])
    assert acc.free_share(grid, world_from_map, free) == 1.0
    assert acc.free_share(grid, world_from_map, np.array([[4.0, 0.0, 0.0]])) == 0.0   # behind the wall


@pytest.mark.slow
@pytest.mark.cpu_bound
def test_replay_of_a_short_flight_scores_both_mappers():
    world = build_world("small_house", 1)
    cam = CameraConfig(width=80, height=60)
    start = world.loop[0]
    heading = world.loop[1] - start
    flight = straight_flight(start, np.arctan2(heading[1], heading[0]), seconds=3.0)
    poses = bench.camera_poses(flight, cam, 0.3)
    frames = bench.render_frames(world, cam, poses)
    config = MapperConfig()
    seen, free = bench.truth_samples(frames, poses, cam, world.shapes, config.max_range, config.resolution, 1)
    assert len(seen) > 100 and len(free) > 100
    assert np.all(acc.surface_distance(seen, world.shapes) < 1e-3)
    grid = bench.replay_coopd(frames, poses, cam, "clear")
    coopd = acc.surface_accuracy(grid, np.eye(4), world.shapes, seen)
    octo = acc.surface_accuracy(*bench.replay_octomap(frames, poses, cam, config), world.shapes, seen)
    for r in (coopd, octo):
        assert r["surface_precision"] > 0.9 and r["surface_recall"] > 0.9


def test_without_the_replay_the_goal_and_tables_leave_out_the_octomap_comparison():
    """--no-replay (autopilot comparisons): the daemons' maps are judged alone, and nothing claims
    coopd beat or lost to OctoMap."""
    good = {"surface_precision": 0.97, "surface_recall": 0.96, "surface_mean_m": 0.03, "surface_p95_m": 0.06}
    low = dict(good, surface_recall=0.90)
    row = {"world": "maze", "drone": 1, "members": [1, 2], "local": good, "global": low}
    goal = bench.goal_checks(row, [good, good])
    assert goal == {"own": True, "global": False, "global_vs_members": False}
    row["goal"] = goal
    table = bench.markdown([row])
    assert "| maze | 1 |" in table and "OctoMap" not in table
    replayed = dict(row, coopd=good, octomap=low)
    assert bench.goal_checks(replayed, [good, good])["coopd_vs_octomap"] is True


def test_range_noise_grows_with_depth_squared_and_leaves_no_return_alone():
    frames = [np.full((60, 80), 1.0, np.float32), np.full((60, 80), 3.0, np.float32)]
    frames[0][0, 0] = np.nan
    noisy = bench.with_range_noise(frames, 0.01, seed=7)
    assert np.isnan(noisy[0][0, 0])
    near, far = noisy[0][1:] - 1.0, noisy[1] - 3.0
    assert 0.008 < np.std(near) < 0.012 and 0.08 < np.std(far) < 0.1     # 0.01 * d^2 at 1 m and 3 m
    again = bench.with_range_noise(frames, 0.01, seed=7)
    assert np.array_equal(noisy[1], again[1])


def test_mapper_settings_take_each_fields_own_type():
    assert bench.mapper_settings("miss_decrement=5,traversal=exact,gap_fill=false") == {
        "miss_decrement": 5, "traversal": "exact", "gap_fill": False}
    for bad in ("nonsense=1", "miss_decrement=five", "gap_fill=flase", "max_range=10",
                "beyond_max_range=drop"):
        with pytest.raises(ValueError):
            bench.mapper_settings(bad)

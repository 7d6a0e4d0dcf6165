import numpy as np
import pytest

from coopd.grid import UNKNOWN
from coopd.mapping import FrameRejected, Intrinsics, Mapper, MapperConfig, Pose
from tests.synthetic_scenes import (
    camera_pose,
    hit_keys,
    occupied_accuracy,
    render_depth,
    room_scene,
    survey_poses,
)

INTR = Intrinsics.from_fov(160, 120, 87.0)


def _fly(config: MapperConfig, scene, poses, noise=0.0, seed=1):
    rng = np.random.default_rng(seed)
    mapper = Mapper(config)
    seen = set()
    for pose in poses:
        depth = render_depth(scene, INTR, pose)
        seen |= hit_keys(depth, INTR, pose, config.resolution, config.min_range, config.max_range)
        if noise:
            depth = (depth * (1 + rng.normal(0, noise, depth.shape))).astype(np.float32)
        mapper.integrate(depth, INTR, pose)
    return mapper, seen


@pytest.fixture(scope="module")
def scene():
    return room_scene(0)


@pytest.mark.parametrize("graze_deg", [20.0, 0.0])
def test_accuracy_with_perfect_poses(scene, graze_deg):
    mapper, seen = _fly(MapperConfig(graze_deg=graze_deg), scene, survey_poses())
    acc = occupied_accuracy(mapper.grid, scene, seen)
    print(f"perfect poses, graze_deg {graze_deg}: P {acc['precision']:.3f} R {acc['recall']:.3f}")
    assert acc["precision"] >= 0.95 and acc["recall"] >= 0.95, acc
    assert acc["free_accuracy"] >= 0.99, acc


@pytest.mark.parametrize("graze_deg", [20.0, 0.0])
def test_accuracy_with_depth_noise(scene, graze_deg):
    mapper, seen = _fly(MapperConfig(graze_deg=graze_deg), scene, survey_poses(), noise=0.01)
    acc = occupied_accuracy(mapper.grid, scene, seen)
    print(f"1 % depth noise, graze_deg {graze_deg}: P {acc['precision']:.3f} R {acc['recall']:.3f}")
    assert acc["precision"] >= 0.93 and acc["recall"] >= 0.95, acc


def test_thesis_per_ray_mode_is_selectable(scene):
    cfg = MapperConfig(per_frame_dedup=False, miss_decrement=30)
    mapper, seen = _fly(cfg, scene, survey_poses(2, 6))
    acc = occupied_accuracy(mapper.grid, scene, seen)
    assert acc["precision"] >= 0.95        # carving is exact; grazing rays cost recall
    assert mapper.grid.counts().occupied > 1000


@pytest.mark.parametrize("traversal", ["bresenham", "exact"])
def test_threads_give_identical_grids(scene, traversal):
    poses = survey_poses(2, 4)
    one, _ = _fly(MapperConfig(threads=1, traversal=traversal), scene, poses)
    two, _ = _fly(MapperConfig(threads=2, traversal=traversal), scene, poses)
    three, _ = _fly(MapperConfig(threads=3, traversal=traversal), scene, poses)
    assert one.grid.same_cells(two.grid) and one.grid.same_cells(three.grid)
    for m in (one, two, three):
        m.close()


def test_shared_path_shortcut_is_exact(scene):
    """Rays ending in one cell share a Bresenham path; walking each (hit_depth > 0 disables the
    shortcut, tiny enough to change nothing else) must give the same grid."""
    poses = survey_poses(2, 4)
    fast, _ = _fly(MapperConfig(hit_depth=0.0), scene, poses)
    slow, _ = _fly(MapperConfig(hit_depth=1e-9), scene, poses)
    assert fast.grid.same_cells(slow.grid)


def _floor_cells(grid) -> int:
    """Occupied cells of the layer that holds the room's floor plane (z = 0)."""
    keys = np.argwhere(grid.cells >= 50) + grid.offset
    return int(np.sum(keys[:, 2] == 0))


@pytest.mark.parametrize("graze_deg, kept_at_least, kept_at_most", [(20.0, 0.99, 1.0), (0.0, 0.0, 0.9)])
def test_a_ray_grazing_the_floor_leaves_it_occupied(scene, graze_deg, kept_at_least, kept_at_most):
    """A drone on the ground: its camera, 3 cm over the floor, looks level across the room after the
    floor was mapped from 1.2 m. Its rays run through the free part of the floor's cells; they spare
    them (graze_deg) but clear them when every ray clears every cell it passes (graze_deg 0)."""
    mapper, _ = _fly(MapperConfig(graze_deg=graze_deg), scene, survey_poses())
    before = _floor_cells(mapper.grid)
    for k in range(12):
        mapper.integrate(render_depth(scene, INTR, camera_pose([0.0, 0.0, 0.03], 2 * np.pi * k / 12)),
                         INTR, camera_pose([0.0, 0.0, 0.03], 2 * np.pi * k / 12))
    kept = _floor_cells(mapper.grid) / before
    assert before > 1000 and kept_at_least <= kept <= kept_at_most, (before, kept)


def test_a_ray_grazing_a_wall_clears_it_as_before(scene):
    """Only level surfaces are spared: a camera 3 cm from the +x wall looking along it clears the
    wall cells its rays run through just as without the guard (a wall that drift mapped twice must
    not stay twice)."""
    lost = []
    for graze_deg in (20.0, 0.0):
        mapper, _ = _fly(MapperConfig(graze_deg=graze_deg), scene, survey_poses())

        def wall_cells(m=mapper):
            keys = np.argwhere(m.grid.cells >= 50) + m.grid.offset
            return {tuple(k) for k in keys[keys[:, 0] == 40].tolist()}

        before = wall_cells()
        for yaw in (np.pi / 2, -np.pi / 2):
            pose = camera_pose([3.97, 0.0, 1.2], yaw)
            mapper.integrate(render_depth(scene, INTR, pose), INTR, pose)
        lost.append(before - wall_cells())
    assert len(lost[1]) > 0 and lost[0] == lost[1], (len(lost[0]), len(lost[1]))


@pytest.mark.parametrize("graze_deg, most_left", [(20.0, 0.08), (0.0, 0.06)])
def test_a_removed_box_is_cleared(scene, graze_deg, most_left):
    """What sparing grazed cells costs: a piece of furniture taken away after the room was mapped is
    cleared by the next survey more slowly, since a cell of its top seen only edge-on afterwards is
    spared. Prints the share of the box's cells still occupied after one survey of 48 frames."""
    mapper, _ = _fly(MapperConfig(graze_deg=graze_deg), scene, survey_poses())
    total = left = 0
    for b in range(6, len(scene.boxes)):  # the furniture (room_scene: six boxes of room first)
        lo, hi = scene.boxes[b]
        gone = type(scene)(np.delete(scene.boxes, b, axis=0))

        def in_box(grid, lo=lo, hi=hi):
            c = (np.argwhere(grid.cells >= 50) + grid.offset) * grid.resolution
            return int(np.sum(np.all((c >= lo - 0.05) & (c <= hi + 0.05), axis=1) & (c[:, 2] > 0.15)))

        after = Mapper(MapperConfig(graze_deg=graze_deg), mapper.grid.copy())
        total += in_box(after.grid)
        for pose in survey_poses():
            after.integrate(render_depth(gone, INTR, pose), INTR, pose)
        left += in_box(after.grid)
    print(f"graze_deg {graze_deg}: {left} of {total} cells of removed boxes left ({left / total:.2f})")
    assert total > 300 and left <= most_left * total


def test_noise_in_free_space_is_cleared_by_any_ray(scene):
    """An occupied cell with free space all round has no surface to graze: rays passing it in any
    direction clear it as before."""
    mapper, _ = _fly(MapperConfig(), scene, survey_poses(2, 6))
    speck = np.array([[1.5, 0.3, 1.2]])
    key = mapper.grid.keys_of(speck)[0] - mapper.grid.offset
    assert 0 <= mapper.grid.cells[tuple(key)] < 50
    mapper.grid.cells[tuple(key)] = 60  # one hit on a fresh cell
    for k in range(12):
        pose = camera_pose([0.0, 0.0, 1.2], 2 * np.pi * k / 12)
        mapper.integrate(render_depth(scene, INTR, pose), INTR, pose)
    assert mapper.grid.values_at(speck)[0] < 50


def test_graze_angle_is_checked():
    with pytest.raises(ValueError, match="graze_deg"):
        MapperConfig(graze_deg=75.0)


def test_single_wall_geometry():
    """A camera 2 m in front of a wall: the wall cells are occupied, the space before it free."""
    from tests.synthetic_scenes import BoxScene
    scene = BoxScene(np.array([[[2.0, -3.0, -3.0], [2.2, 3.0, 3.0]]]))
    pose = camera_pose([0.0, 0.0, 0.0], yaw=0.0)
    depth = render_depth(scene, INTR, pose)
    assert np.allclose(depth[60, 80], 2.0, atol=1e-6)
    mapper = Mapper(MapperConfig(gap_fill=False))
    stats = mapper.integrate(depth, INTR, pose)
    assert stats.rays == 160 * 120 and stats.invalid_pixels == 0
    g = mapper.grid
    assert g.values_at_keys([[20, 0, 0]])[0] == 60           # unknown -> 50 -> +10
    assert np.all(g.values_at_keys([[k, 0, 0] for k in range(1, 20)]) == 35)   # 50 - 15
    assert g.values_at_keys([[21, 0, 0]])[0] == UNKNOWN       # behind the wall


def test_max_range_truncates_without_hits():
    from tests.synthetic_scenes import BoxScene
    scene = BoxScene(np.array([[[8.0, -30.0, -30.0], [8.2, 30.0, 30.0]]]))
    pose = camera_pose([0.0, 0.0, 0.0], yaw=0.0)
    depth = render_depth(scene, INTR, pose)
    mapper = Mapper(MapperConfig(max_range=5.0, gap_fill=False, beyond_max_range="drop"))
    stats = mapper.integrate(depth, INTR, pose)
    assert stats.invalid_pixels == 160 * 120 and stats.rays == 0      # z = 8 m > max range
    assert mapper.grid.counts().known == 0
    depth2 = np.full_like(depth, 4.5)                                  # corners longer than 5 m
    stats2 = mapper.integrate(depth2, INTR, pose)
    assert stats2.truncated_rays > 0 and 0 < stats2.hits < stats2.cells_updated
    assert mapper.grid.counts().occupied > 0
    far = mapper.grid.values_at([[0.0, 0.0, 4.5]])   # optical z is forward = map x for yaw 0
    assert far[0] == UNKNOWN


@pytest.mark.parametrize("z16", [False, True])
def test_readings_beyond_max_range_clear_up_to_it_and_mark_no_hit(z16):
    """A wall 8 m away seen with max range 5 m (OctoMap's maxrange): every pixel is a ray cut at
    5 m; the cells along it up to 5 m are free, none is occupied, nothing beyond 5 m is touched."""
    from tests.synthetic_scenes import BoxScene
    scene = BoxScene(np.array([[[8.0, -30.0, -30.0], [8.2, 30.0, 30.0]]]))
    pose = camera_pose([0.0, 0.0, 0.0], yaw=0.0)
    depth = render_depth(scene, INTR, pose)
    intr = INTR
    if z16:
        depth = np.round(depth / 0.001).astype(np.uint16)
        intr = Intrinsics.from_fov(160, 120, 87.0, depth_scale=0.001)
    mapper = Mapper(MapperConfig(max_range=5.0, gap_fill=False))
    stats = mapper.integrate(depth, intr, pose)
    assert stats.rays == 160 * 120 and stats.truncated_rays == 160 * 120 and stats.invalid_pixels == 0
    assert stats.hits == 0 and stats.cells_updated > 0
    g = mapper.grid
    assert g.counts().occupied == 0
    # Along the optical axis (map +x for yaw 0): cells 1..49 free (50 - 15), nothing past 5 m.
    assert np.all(g.values_at_keys([[k, 0, 0] for k in range(1, 50)]) == 35)
    assert np.all(g.values_at_keys([[k, 0, 0] for k in range(51, 60)]) == UNKNOWN)
    known = np.argwhere(g.cells >= 0) + g.offset
    assert np.max(np.linalg.norm(known * g.resolution, axis=1)) <= 5.0 + g.resolution


@pytest.mark.parametrize("fill", [0.0, np.nan, np.inf, -1.0, 2000.0])
def test_no_reading_is_not_a_far_reading(fill):
    """Depth 0 (no return), NaN, inf, negative or beyond any camera's reach clears nothing, even
    where a beyond-max-range reading would."""
    mapper = Mapper(MapperConfig(max_range=5.0))
    depth = np.full((120, 160), 8.0, np.float32)
    depth[:, :80] = fill
    stats = mapper.integrate(depth, INTR, GOOD_POSE)
    assert stats.invalid_pixels == 120 * 80 and stats.rays == 120 * 80
    g = mapper.grid
    known = np.argwhere(g.cells >= 0) + g.offset
    # Optical x is right = map -y: the left half of the image (u < 80) looks to map +y.
    assert len(known) and np.all(known[:, 1] <= 1)


def test_z16_and_float_frames_agree(scene):
    pose = survey_poses(1, 1)[0]
    depth = render_depth(scene, INTR, pose)
    z16 = np.round(depth / 0.001).astype(np.uint16)
    a, b = Mapper(), Mapper()
    a.integrate(depth, INTR, pose)
    b.integrate(z16, Intrinsics.from_fov(160, 120, 87.0, depth_scale=0.001), pose)
    diff = np.argwhere(a.grid.cells != b.grid.cells)
    assert len(diff) < 0.001 * a.grid.counts().known    # mm rounding moves a handful of end cells


def test_grid_grows_as_rays_leave_it(scene):
    mapper = Mapper(MapperConfig())
    assert mapper.grid.shape == (40, 40, 20)
    stats = mapper.integrate(render_depth(scene, INTR, survey_poses(1, 1)[0]), INTR, survey_poses(1, 1)[0])
    assert stats.grew and mapper.grid.shape[0] > 40
    lo, hi = mapper.grid.known_key_bounds()
    glo, ghi = mapper.grid.key_bounds()
    assert np.all(lo - glo >= mapper.grid.growth.margin) and np.all(ghi - hi >= mapper.grid.growth.margin)


# ----------------------------------------------------------------------------- hostile input
GOOD_POSE = camera_pose([0.0, 0.0, 1.0], 0.0)


@pytest.mark.parametrize("depth", [
    np.zeros((120, 161), np.float32),               # wrong shape
    np.zeros((120, 160), np.int32),                 # wrong dtype
    np.zeros((120, 160, 3), np.uint16),             # colour image
    [[1.0] * 160] * 120,                            # not an array
])
def test_bad_frames_are_rejected_and_grid_unchanged(depth):
    mapper = Mapper()
    before = mapper.grid.cells.copy()
    with pytest.raises(FrameRejected):
        mapper.integrate(depth, INTR, GOOD_POSE)
    assert np.array_equal(mapper.grid.cells, before)
    assert mapper.totals.frames_rejected == 1


@pytest.mark.parametrize("fill", [np.nan, 0.0, np.inf, -1.0, 1e30])
def test_invalid_pixels_are_skipped_and_counted(fill):
    mapper = Mapper()
    before = mapper.grid.cells.copy()
    stats = mapper.integrate(np.full((120, 160), fill, np.float32), INTR, GOOD_POSE)
    assert stats.rays == 0 and stats.invalid_pixels == 160 * 120
    assert np.array_equal(mapper.grid.cells, before)


@pytest.mark.parametrize("kwargs", [
    dict(width=160, height=120, fx=0.0, fy=100.0, cx=80.0, cy=60.0),
    dict(width=160, height=120, fx=np.nan, fy=100.0, cx=80.0, cy=60.0),
    dict(width=160, height=120, fx=100.0, fy=100.0, cx=1e9, cy=60.0),
    dict(width=0, height=120, fx=100.0, fy=100.0, cx=80.0, cy=60.0),
    dict(width=100000, height=120, fx=100.0, fy=100.0, cx=80.0, cy=60.0),
    dict(width=160, height=120, fx=100.0, fy=100.0, cx=80.0, cy=60.0, depth_scale=0.0),
])
def test_absurd_intrinsics_are_rejected(kwargs):
    with pytest.raises(FrameRejected):
        Intrinsics(**kwargs)


def test_real_cameras_are_plausible_and_absurd_ones_say_why():
    d435 = Intrinsics(640, 480, 383.0, 383.0, 319.5, 239.5, 0.001)  # 79.7 x 64.1 deg
    assert d435.implausible() is None
    assert Intrinsics.from_fov(848, 480, 87.0, 1e-4).implausible() is None
    assert Intrinsics.from_fov(160, 120, 165.0).implausible() is None
    for kwargs, words in (
        (dict(fx=0.2), "horizontal field of view 180 deg"),
        (dict(fy=1e5), "vertical field of view"),
        (dict(cx=700.0), "principal point (700, 239.5) px outside the 640x480 image"),
        (dict(cy=-1.0), "principal point"),
        (dict(depth_scale=2e-6), "depth scale 2e-06 m/unit"),
        (dict(depth_scale=0.5), "z16 would span 32767.5 m"),
    ):
        fields = dict(width=640, height=480, fx=383.0, fy=383.0, cx=319.5, cy=239.5, depth_scale=0.001)
        problem = Intrinsics(**dict(fields, **kwargs)).implausible()
        assert problem is not None and words in problem, (kwargs, problem)


@pytest.mark.parametrize("position,quaternion", [
    ([np.nan, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0]),
    ([0.0, 0.0, 0.0], [np.nan, 0.0, 0.0, 0.0]),
    ([0.0, 0.0, 0.0], [2.0, 0.0, 0.0, 0.0]),          # not unit
    ([0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0]),
    ([0.0, 0.0], [1.0, 0.0, 0.0, 0.0]),
])
def test_bad_poses_are_rejected(position, quaternion):
    with pytest.raises(FrameRejected):
        Pose(position, quaternion)


def test_slightly_off_unit_quaternion_is_normalised():
    p = Pose([0, 0, 0], [1.02, 0.0, 0.0, 0.0])
    assert np.isclose(np.linalg.norm(p.quaternion), 1.0)


def test_far_away_pose_cannot_allocate_without_bound():
    mapper = Mapper()
    pose = camera_pose([1e6, 0.0, 0.0], 0.0)
    before = mapper.grid.cells.copy()
    with pytest.raises(FrameRejected):
        mapper.integrate(np.full((120, 160), 2.0, np.float32), INTR, pose)
    assert np.array_equal(mapper.grid.cells, before)


def test_config_validation_names_the_problem():
    with pytest.raises(ValueError, match="beyond_max_range"):
        MapperConfig(beyond_max_range="ignore")
    with pytest.raises(ValueError, match="traversal"):
        MapperConfig(traversal="magic")
    with pytest.raises(ValueError, match="range"):
        MapperConfig(min_range=5.0, max_range=1.0)

import numpy as np
import pytest
from scipy.spatial import cKDTree

from coopd.geometry import apply, invert, rigid, rotation_z
from coopd.grid import transform_grid
from coopd.merging.brief3d import describe, make_sample
from coopd.merging.features import extract
from coopd.merging.matching import hamming_block
from coopd.merging.orientation import orientations
from coopd.merging.params import MergeParams
from firmware_sim.benchset import make_world, partial_map


def _scene(seed=3):
    """An asymmetric room: walls, a floor and a few boxes, as an intensity image."""
    rng = np.random.default_rng(seed)
    img = np.zeros((48, 48, 24), dtype=np.float32)
    img[:, :, :2] = 240
    img[:3] = 240
    img[:, :3] = 240
    for _ in range(6):
        x, y = rng.integers(5, 40, 2)
        sx, sy, sz = rng.integers(2, 7, 3)
        img[x:x + sx, y:y + sy, 2:2 + sz] = 240
    return img


def _rot90_key(k, shape):
    """Index of cell k after np.rot90(img, 1, axes=(0, 1)) (a +90 degree yaw of the grid)."""
    x, y, z = k
    return np.array([shape[1] - 1 - y, x, z])


def test_sample_is_seeded_and_inside_the_window():
    s = make_sample(256, 31, 42)
    assert s.shape == (512, 3) and np.abs(s).max() <= 15.5
    assert np.array_equal(s, make_sample(256, 31, 42))


def test_steered_descriptor_is_invariant_to_a_90_degree_yaw_of_the_grid():
    params = MergeParams(gravity_aligned=True, descriptor_window=15)
    img = _scene()
    rot = np.ascontiguousarray(np.rot90(img, 1, axes=(0, 1)))
    kp = np.array([[10, 12, 5], [20, 30, 6], [33, 18, 4], [14, 36, 8]], dtype=np.int64)
    kr = np.array([_rot90_key(k, img.shape) for k in kp], dtype=np.int64)
    da = describe(img, kp, orientations(img, kp, params), params)
    db = describe(rot, kr, orientations(rot, kr, params), params)
    ang_a = orientations(img, kp, params)[:, 2]
    ang_b = orientations(rot, kr, params)[:, 2]
    # Gauss-Seidel sweeps in a fixed order, so the field turns with the grid only approximately
    assert np.allclose(np.angle(np.exp(1j * (ang_b - ang_a - np.pi / 2))), 0, atol=0.25)
    d = hamming_block(da, db)
    same = np.diag(d)
    assert same.max() <= 26  # up to resampling of rounded sample points (of 256 tests)
    assert same.max() < np.median(d[~np.eye(len(kp), dtype=bool)])


def test_unsteered_descriptor_is_not_invariant():
    """The check above can fail: without steering a 90 degree turn changes the descriptor a lot."""
    params = MergeParams(gravity_aligned=True, descriptor_window=15)
    img = _scene()
    rot = np.ascontiguousarray(np.rot90(img, 1, axes=(0, 1)))
    kp = np.array([[4, 12, 3], [20, 4, 3]], dtype=np.int64)  # next to a wall and the floor
    kr = np.array([_rot90_key(k, img.shape) for k in kp], dtype=np.int64)
    zero = np.zeros((2, 3))
    d = hamming_block(describe(img, kp, zero, params), describe(rot, kr, zero, params))
    steered = hamming_block(describe(img, kp, orientations(img, kp, params), params),
                            describe(rot, kr, orientations(rot, kr, params), params))
    assert np.diag(d).min() > 40
    assert np.diag(steered).max() < np.diag(d).min()


def test_local_and_global_orientation_agree_near_a_wall():
    img = np.zeros((30, 30, 30), dtype=np.float32)
    img[:5] = 250
    kp = np.array([[7, 15, 15]], dtype=np.int64)
    g = orientations(img, kp, MergeParams(orientation_mode="global"))
    loc = orientations(img, kp, MergeParams(orientation_mode="local"))
    # the field falls away from the wall at x < 5: yaw points along +x
    assert abs(g[0, 2]) < 0.05 and abs(loc[0, 2]) < 0.05


@pytest.mark.parametrize("deg", [90, 180])
def test_yaw_steering_matches_a_turned_copy_within_cc_d_and_euler_steering_does_not(deg):
    """A lossless copy of a map turned by deg: the true correspondences' Hamming distances are inside
    CC_d = 20 when the sample turns by yaw only, and random (about half of 256) when it turns by the
    full alpha, beta, gamma of eq. 20 (alpha and beta mix horizontal gradient components)."""
    world = make_world(3, size_m=(12.0, 12.0, 3.0))
    grid = partial_map(world, rigid(np.eye(3), [6.0, 6.0, 1.5]), ((1, 1), (11, 11)),
                       np.random.default_rng(1), viewpoints=10, rays=4000).grid
    t = rigid(rotation_z(np.radians(deg)), [2.0, -1.0, 0.0])
    turned = transform_grid(grid, t)
    medians = {}
    for steering in ("yaw", "euler"):
        params = MergeParams(fast_both_polarities=True, descriptor_steering=steering)
        fa, fb = extract(grid, params), extract(turned, params)
        dist, nearest = cKDTree(apply(invert(t), fb.points_m)).query(fa.points_m)
        same = dist < fa.cell_m  # block parity may move a keypoint by half a block per axis
        assert same.sum() >= 50
        d = hamming_block(fa.descriptors[same], fb.descriptors[nearest[same]])
        medians[steering] = float(np.median(np.diag(d)))
    print(f"{deg} deg copy, median Hamming distance of true correspondences: {medians}")
    assert medians["yaw"] <= MergeParams().match_max_distance, medians
    assert medians["euler"] > 60, medians


def test_unknown_steering_is_refused():
    with pytest.raises(ValueError, match="descriptor_steering"):
        describe(np.zeros((4, 4, 4), np.float32), np.array([[1, 1, 1]]), np.zeros((1, 3)),
                 MergeParams(descriptor_steering="roll"))

"""Keypoint orientations follow a yaw turn of the map at any angle (0-360 degrees in 15 degree steps)."""

import numpy as np
import pytest

from coopd.geometry import apply, rigid, rotation_z
from coopd.grid import transform_grid
from coopd.merging.fast3d import fast3d
from coopd.merging.keypoint_filter import filter_keypoints
from coopd.merging.orientation import orientations
from coopd.merging.params import MergeParams
from coopd.merging.preprocess import preprocess
from firmware_sim.benchset import make_world, partial_map

ANGLES = range(0, 360, 15)


@pytest.fixture(scope="module")
def room_map():
    world = make_world(3, size_m=(12.0, 12.0, 3.0))
    rng = np.random.default_rng(1)
    return partial_map(world, rigid(np.eye(3), [6.0, 6.0, 1.5]), ((1, 1), (11, 11)), rng,
                       viewpoints=10, rays=4000).grid


def yaw_errors_deg(grid, params, angles=ANGLES, keypoints=200):
    """Median |yaw error| of the keypoints of `grid` re-oriented in copies turned by each angle (the
    copies are resampled by transform_grid, shifted by an odd number of cells so blocks change too)."""
    fi = preprocess(grid, params)
    kp, _ = filter_keypoints(fi.image, fast3d(fi.image, fi.known, params), params)
    kp = kp[:keypoints]
    yaw = orientations(fi.image, kp, params)[:, 2]
    pts = fi.to_metres(kp)
    out = []
    for deg in angles:
        t = rigid(rotation_z(np.radians(deg)), [0.3, -0.1, 0.0])
        turned = preprocess(transform_grid(grid, t), params)
        idx = np.round((apply(t, pts) - turned.origin_m) / turned.cell_m).astype(np.int64)
        inside = np.all((idx >= 0) & (idx < np.array(turned.image.shape)), axis=1)
        got = orientations(turned.image, idx[inside], params)[:, 2]
        err = np.abs(np.angle(np.exp(1j * (got - yaw[inside] - np.radians(deg)))))
        out.append(float(np.degrees(np.median(err))))
    return np.array(out)


def test_orientation_repeats_at_every_yaw(room_map):
    errs = yaw_errors_deg(room_map, MergeParams(fast_both_polarities=True))
    print(f"median yaw error per 15-degree step, max {errs.max():.1f} deg: {errs.round(1).tolist()}")
    assert errs.max() < 8.0, dict(zip(ANGLES, errs.round(1), strict=True))


def test_the_thesis_reading_of_the_gradient_does_not(room_map):
    """The check above can fail: one central difference of an in-place Gauss-Seidel field (eq. 20 read
    literally) moves by 15-30 degrees under the same turns."""
    params = MergeParams(fast_both_polarities=True, orientation_solver="gauss_seidel", orientation_window=0)
    errs = yaw_errors_deg(room_map, params, angles=(45, 90, 180))
    print(f"thesis reading, median yaw error at 45/90/180 deg: {errs.round(1).tolist()}")
    assert errs.max() > 12.0


def test_jacobi_field_turns_exactly_with_a_quarter_turn_of_the_image():
    rng = np.random.default_rng(0)
    img = np.zeros((24, 24, 12), dtype=np.float32)
    for _ in range(8):
        x, y = rng.integers(2, 20, 2)
        img[x:x + 3, y:y + 2, 2:9] = 250
    kp = np.array([[5, 6, 5], [12, 15, 4], [18, 4, 6]], dtype=np.int64)
    turned = np.ascontiguousarray(np.rot90(img, 1, axes=(0, 1)))
    kt = np.array([[img.shape[1] - 1 - y, x, z] for x, y, z in kp], dtype=np.int64)
    for solver, exact in (("jacobi", True), ("gauss_seidel", False)):
        params = MergeParams(orientation_solver=solver)
        a = orientations(img, kp, params)[:, 2]
        b = orientations(turned, kt, params)[:, 2]
        err = np.abs(np.angle(np.exp(1j * (b - a - np.pi / 2))))
        assert (err.max() < 1e-6) == exact, (solver, err)


def test_unknown_solver_is_refused():
    with pytest.raises(ValueError, match="orientation_solver"):
        orientations(np.zeros((4, 4, 4)), np.array([[1, 1, 1]]), MergeParams(orientation_solver="sor"))

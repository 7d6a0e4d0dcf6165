import numpy as np
import pytest

from coopd.merging.fast3d import circle_mask, fast3d, window_max
from coopd.merging.keypoint_filter import filter_keypoints, score_v
from coopd.merging.params import MergeParams
from coopd.merging.preprocess import intensity


def test_circle_of_radius_three_is_the_16_cell_fast_ring():
    m = circle_mask(3)
    assert len(m) == 16
    assert np.all(np.abs(np.hypot(m[:, 0], m[:, 1]) - 3) < 0.5)
    ang = np.arctan2(m[:, 1], m[:, 0])
    assert np.all(np.diff(ang) > 0)


def _corner_image():
    """Free space with an occupied L-shaped corner of two walls and a floor (a box corner)."""
    cells = np.full((20, 20, 20), 5, dtype=np.int8)
    cells[:4, :, :] = 95
    cells[:, :4, :] = 95
    cells[:, :, :4] = 95
    return intensity(cells)


def test_inner_corner_of_a_box_is_a_fast3d_keypoint_and_open_space_is_not():
    img = _corner_image()
    known = np.ones(img.shape, dtype=bool)
    kp = fast3d(img, known, MergeParams(fast_both_polarities=False))
    keys = {tuple(k) for k in kp}
    assert (4, 4, 4) in keys
    assert not any(min(k) >= 9 for k in keys)  # nothing in open space


def test_flat_wall_alone_is_not_a_keypoint():
    cells = np.full((20, 20, 20), 5, dtype=np.int8)
    cells[:4] = 95
    kp = fast3d(intensity(cells), np.ones(cells.shape, dtype=bool), MergeParams(fast_both_polarities=False))
    assert len(kp) == 0


def test_unknown_cells_are_never_keypoints():
    img = _corner_image()
    kp = fast3d(img, np.zeros(img.shape, dtype=bool), MergeParams())
    assert len(kp) == 0


def test_filter_keeps_one_local_maximum_of_score_v():
    img = _corner_image()
    kp = fast3d(img, np.ones(img.shape, dtype=bool), MergeParams(fast_both_polarities=False))
    fk, sc = filter_keypoints(img, kp, MergeParams(filter_adjacent_radius=3.0))
    assert len(fk) < len(kp)
    full = score_v(img, kp, 1)
    assert sc[0] == full.max()
    d = np.linalg.norm(fk[:, None, :] - fk[None, :, :], axis=2) + np.eye(len(fk)) * 99
    assert d.min() > 3.0


@pytest.mark.parametrize("shape, reach", [((40, 30, 12), 6), ((5, 7, 3), 4), ((3, 300, 2), 1), ((1, 1, 1), 2),
                                          ((9, 4, 600), 0)])
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_window_max_is_scipys_constant_mode_maximum_filter(shape, reach, dtype):
    """The contrast prefilter's max and min over a cube (outside reads 0) equal scipy.ndimage's,
    including windows wider than the image and more columns than one chunk."""
    from scipy import ndimage

    rng = np.random.default_rng(sum(shape) + reach)
    img = np.where(rng.random(shape) < 0.6, rng.random(shape) * 255, 0).astype(dtype)
    size = 2 * reach + 1
    assert np.array_equal(window_max(img, reach), ndimage.maximum_filter(img, size=size, mode="constant"))
    assert np.array_equal(-window_max(-img, reach), ndimage.minimum_filter(img, size=size, mode="constant"))

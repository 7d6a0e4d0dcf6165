import numpy as np

from coopd.grid import OccupancyGrid
from coopd.merging.params import MergeParams
from coopd.merging.preprocess import dilate, downsample, erode, gaussian, intensity, preprocess


def test_intensity_maps_occupancy_to_255_and_unknown_to_zero():
    cells = np.array([[[-1, -2, 0, 50, 100]]], dtype=np.int8)
    assert np.allclose(intensity(cells), [[[0, 0, 0, 127.5, 255]]])


def test_dilate_then_erode_closes_a_one_cell_hole_in_a_wall():
    img = np.zeros((9, 9, 9), dtype=np.float32)
    img[4, :, :] = 255
    img[4, 4, 4] = 0
    closed = erode(dilate(img, 1), 1)
    assert closed[4, 4, 4] == 255
    assert closed[2, 4, 4] == 0 and closed[6, 4, 4] == 0


def test_gaussian_keeps_mass_away_from_borders_and_spreads_a_spike():
    img = np.zeros((15, 15, 15), dtype=np.float32)
    img[7, 7, 7] = 1000
    g = gaussian(img, 3, 1.0)
    assert abs(g.sum() - 1000) < 1
    assert g[7, 7, 7] < 1000 and g[8, 7, 7] > 0 and g[7, 7, 11] == 0


def test_downsample_averages_blocks_and_marks_known_blocks():
    img = np.arange(64, dtype=np.float32).reshape(4, 4, 4)
    known = np.zeros((4, 4, 4), dtype=bool)
    known[0, 0, 0] = True
    out, kn = downsample(img, known, 1)
    assert out.shape == (2, 2, 2)
    assert out[0, 0, 0] == img[:2, :2, :2].mean()
    assert kn[0, 0, 0] and not kn[1, 1, 1]


def test_preprocess_places_downsampled_cells_in_metres():
    g = OccupancyGrid(np.full((10, 10, 10), 10, dtype=np.int8), 0.1, (-5, -5, 0))
    fi = preprocess(g, MergeParams())
    # block [0..1] of keys -5,-4 has its centre at -4.5 keys = -0.45 m
    assert np.allclose(fi.to_metres([0, 0, 0]), [-0.45, -0.45, 0.05])
    assert fi.cell_m == 0.2 and fi.image.shape == (5, 5, 5)

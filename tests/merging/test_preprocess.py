from pathlib import Path

import numpy as np

from coopd.grid import OccupancyGrid
from coopd.io.cmap import load_cmap
from coopd.merging.params import MergeParams
from coopd.merging.preprocess import despeckle, dilate, downsample, erode, gaussian, intensity, preprocess

DATA = Path(__file__).parent / "data"


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


def _flipped(grid, fraction, seed=0):
    """A copy with `fraction` of the known cells flipped (occupied <-> free): salt-and-pepper noise."""
    rng = np.random.default_rng(seed)
    cells = grid.cells.copy()
    flat = cells.reshape(-1)
    known = np.flatnonzero(flat >= 0)
    pick = rng.choice(known, int(fraction * len(known)), replace=False)
    flat[pick] = np.where(flat[pick] >= 50, 10, 90)
    return OccupancyGrid(cells, grid.resolution, grid.offset)


def test_despeckle_removes_salt_noise_and_keeps_surfaces(near_pair):
    clean = near_pair.a
    noisy = _flipped(clean, 0.10)
    out = despeckle(noisy, MergeParams())
    was_surface = clean.cells >= 50
    near_surface = dilate(was_surface.astype(np.float32), 1) > 0
    speckle = (noisy.cells >= 50) & ~near_surface  # one touching a wall only thickens it
    assert speckle.sum() > 0.5 * was_surface.sum()
    kept_speckle = (out.cells >= 50) & speckle
    # most speckles go; the rest float where the ray-cast map is mostly unknown (sparse far rays)
    assert kept_speckle.sum() < 0.25 * speckle.sum()
    noisy_surface = was_surface & (noisy.cells >= 50)
    assert ((out.cells >= 50) & noisy_surface).sum() > 0.95 * noisy_surface.sum()
    assert (out.cells[speckle & ~kept_speckle] == -1).all()  # removed evidence becomes unknown, never free


def test_despeckle_leaves_real_flight_maps_almost_whole():
    for name in ("early_1", "later_2"):
        grid, _ = load_cmap(DATA / "small_house_flip" / f"{name}.cmap")
        out = despeckle(grid, MergeParams())
        assert (out.cells >= 50).sum() > 0.99 * (grid.cells >= 50).sum()


def test_despeckle_off_or_clean_returns_the_grid_itself(near_pair):
    assert despeckle(near_pair.a, MergeParams(despeckle_max_occupied=-1)) is near_pair.a
    assert despeckle(near_pair.a, MergeParams()) is near_pair.a  # clean: its few lone cells are real
    noisy = _flipped(near_pair.a, 0.02)
    assert despeckle(noisy, MergeParams()) is not noisy
    lone = OccupancyGrid(np.full((5, 5, 5), 10, dtype=np.int8), 0.1)
    assert despeckle(lone, MergeParams()) is lone

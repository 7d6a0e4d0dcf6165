"""Preprocessing (§8.1): intensity image, dilate, erode, Gaussian smoothing, downsampling.

The occupancy grid becomes an image of intensities 0..255 (occupancy * 2.55, as the FAST threshold
th = 80 is an image threshold); unknown and inaccessible cells read 0, like free space, so the border
of the explored region is not mistaken for a structure of the world.
"""

from dataclasses import dataclass

import numba as nb
import numpy as np
from scipy import ndimage

from ..grid import OccupancyGrid
from .params import MergeParams

_JIT = {"nogil": True, "cache": True}


@dataclass(frozen=True)
class FeatureImage:
    """A preprocessed map: intensities, which cells were known, and where cell [0,0,0] is (metres)."""

    image: np.ndarray
    known: np.ndarray
    origin_m: np.ndarray
    cell_m: float

    def to_metres(self, idx: np.ndarray) -> np.ndarray:
        """Map-frame centres (metres) of image cells given by array index (…, 3)."""
        return self.origin_m + np.asarray(idx, dtype=np.float64) * self.cell_m


def intensity(cells: np.ndarray) -> np.ndarray:
    """float32 image 0..255 of int8 occupancy cells (unknown/inaccessible -> 0)."""
    return np.where(cells >= 0, cells.astype(np.float32) * np.float32(2.55), np.float32(0.0))


def dilate(img: np.ndarray, radius: int = 1, iterations: int = 1) -> np.ndarray:
    """Grey dilation with a cube of half-size radius (windows clipped at the borders)."""
    img = np.asarray(img, dtype=np.float32)
    for _ in range(iterations):
        for axis in range(3):
            img = ndimage.maximum_filter1d(img, 2 * radius + 1, axis=axis, mode="nearest")
    return img


def erode(img: np.ndarray, radius: int = 1, iterations: int = 1) -> np.ndarray:
    """Grey erosion with a cube of half-size radius (windows clipped at the borders)."""
    img = np.asarray(img, dtype=np.float32)
    for _ in range(iterations):
        for axis in range(3):
            img = ndimage.minimum_filter1d(img, 2 * radius + 1, axis=axis, mode="nearest")
    return img


def gaussian(img: np.ndarray, radius: int = 3, sigma: float = 1.0, iterations: int = 1) -> np.ndarray:
    """Separable Gaussian smoothing truncated at radius cells; near the borders the weights inside
    the image are renormalised (outside is no evidence, not zero intensity)."""
    x = np.arange(-radius, radius + 1, dtype=np.float64)
    w = np.exp(-0.5 * (x / sigma) ** 2)
    img = np.asarray(img, dtype=np.float32)
    for _ in range(iterations):
        for axis in range(3):
            n = img.shape[axis]
            shape = [1, 1, 1]
            shape[axis] = n
            norm = ndimage.correlate1d(np.ones(n), w, mode="constant").reshape(shape).astype(np.float32)
            img = ndimage.correlate1d(img, w.astype(np.float32), axis=axis, mode="constant") / norm
    return img


@nb.njit(**_JIT)
def _block_mean(img, known, f, out, out_known):
    """Average f^3 blocks of img; a block is known when any of its cells is."""
    for i in range(out.shape[0]):
        for j in range(out.shape[1]):
            for k in range(out.shape[2]):
                acc = 0.0
                kn = False
                for a in range(f):
                    for b in range(f):
                        for c in range(f):
                            acc += img[i * f + a, j * f + b, k * f + c]
                            kn = kn or known[i * f + a, j * f + b, k * f + c]
                out[i, j, k] = acc / (f * f * f)
                out_known[i, j, k] = kn


def downsample(img: np.ndarray, known: np.ndarray, radius: int = 1):
    """Block means with factor 2*radius per axis (eq. 34); radius 0 leaves the image as it is."""
    f = max(1, 2 * radius)
    shape = tuple(max(1, s // f) for s in img.shape)
    pad = [(0, max(0, sh * f - s)) for sh, s in zip(shape, img.shape, strict=True)]
    if any(p[1] for p in pad):
        img, known = np.pad(img, pad), np.pad(known, pad)
    out = np.empty(shape, dtype=np.float32)
    out_known = np.empty(shape, dtype=np.bool_)
    _block_mean(img, known, f, out, out_known)
    return out, out_known


def preprocess(grid: OccupancyGrid, params: MergeParams) -> FeatureImage:
    """§8.1 in order: dilate, erode, Gaussian, downsample; returns the image features are found on."""
    img = intensity(grid.cells)
    img = dilate(img, params.dilate_radius, params.dilate_iterations)
    img = erode(img, params.erode_radius, params.erode_iterations)
    img = gaussian(img, params.gaussian_radius, params.gaussian_sigma, params.gaussian_iterations)
    img, known = downsample(img, grid.cells != -1, params.downsample_radius)
    f = max(1, 2 * params.downsample_radius)
    origin = (grid.offset + (f - 1) / 2.0) * grid.resolution
    return FeatureImage(img, known, origin, f * grid.resolution)


@nb.njit(**_JIT)
def _speckles(cells, threshold, max_occupied):
    """Mask of occupied cells with at most max_occupied occupied neighbours (of 26) and more free
    neighbours than unknown ones."""
    mx, my, mz = cells.shape
    out = np.zeros(cells.shape, dtype=np.bool_)
    for x in range(mx):
        for y in range(my):
            for z in range(mz):
                if cells[x, y, z] < threshold:
                    continue
                occ = -1
                free = 0
                unknown = 26 - (min(mx, x + 2) - max(0, x - 1)) * (min(my, y + 2) - max(0, y - 1)) \
                    * (min(mz, z + 2) - max(0, z - 1)) + 1
                for a in range(max(0, x - 1), min(mx, x + 2)):
                    for b in range(max(0, y - 1), min(my, y + 2)):
                        for c in range(max(0, z - 1), min(mz, z + 2)):
                            v = cells[a, b, c]
                            if v >= threshold:
                                occ += 1
                            elif v >= 0:
                                free += 1
                            else:
                                unknown += 1
                out[x, y, z] = occ <= max_occupied and free > unknown
    return out


def despeckle(grid: OccupancyGrid, params: MergeParams) -> OccupancyGrid:
    """The grid without salt noise: an occupied cell with at most despeckle_max_occupied occupied
    neighbours (of 26) and more free neighbours than unknown ones becomes unknown, when such cells are
    at least despeckle_min_share of the occupied cells. A surface the sensor saw has its own occupied
    neighbours, or unknown space behind it as much as free space in front; a flipped cell floating in
    free space has neither. Clean maps hold few such cells (mostly real, e.g. thin poles) and stay
    as they are; 2 % of flipped cells pass despeckle_min_share. On such a map the filter runs
    despeckle_passes times: a speckle that leaned on others loses them in the pass before. Unknown,
    not free: the filter removes evidence, it never invents free space. The grid itself when nothing
    is removed."""
    if params.despeckle_max_occupied < 0:
        return grid
    drop = _speckles(grid.cells, params.occupied_threshold, params.despeckle_max_occupied)
    occupied = int((grid.cells >= params.occupied_threshold).sum())
    if not drop.any() or drop.sum() < params.despeckle_min_share * occupied:
        return grid
    cells = grid.cells.copy()
    for _ in range(params.despeckle_passes):
        cells[drop] = -1
        drop = _speckles(cells, params.occupied_threshold, params.despeckle_max_occupied)
        if not drop.any():
            break
    return OccupancyGrid(cells, grid.resolution, grid.offset)

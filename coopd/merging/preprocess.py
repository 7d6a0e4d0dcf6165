"""Preprocessing (§8.1): intensity image, dilate, erode, Gaussian smoothing, downsampling.

The occupancy grid becomes an image of intensities 0..255 (occupancy * 2.55, as the FAST threshold
th = 80 is an image threshold); unknown and inaccessible cells read 0, like free space, so the border
of the explored region is not mistaken for a structure of the world.
"""

from dataclasses import dataclass

import numba as nb
import numpy as np

from coopd.kernel_cache import CACHE as KERNEL_CACHE

from ..grid import OccupancyGrid
from .params import MergeParams

_JIT = {"nogil": True, "cache": KERNEL_CACHE}


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


def _extreme(img: np.ndarray, radius: int, iterations: int, pick) -> np.ndarray:
    """pick (np.maximum or np.minimum) over a cube of half-size radius, one axis at a time; windows are
    clipped at the borders. Whole-slab array operations: no per-line overhead, any dtype."""
    img = np.asarray(img)
    for _ in range(iterations):
        for axis in range(3):
            src, out = img, img.copy()
            n = img.shape[axis]
            for d in range(1, radius + 1):
                head = tuple(slice(0, n - d) if a == axis else slice(None) for a in range(3))
                tail = tuple(slice(d, n) if a == axis else slice(None) for a in range(3))
                pick(out[head], src[tail], out=out[head])
                pick(out[tail], src[head], out=out[tail])
            img = out
    return img


def dilate(img: np.ndarray, radius: int = 1, iterations: int = 1) -> np.ndarray:
    """Grey dilation with a cube of half-size radius (windows clipped at the borders)."""
    return _extreme(img, radius, iterations, np.maximum)


def erode(img: np.ndarray, radius: int = 1, iterations: int = 1) -> np.ndarray:
    """Grey erosion with a cube of half-size radius (windows clipped at the borders)."""
    return _extreme(img, radius, iterations, np.minimum)


def axis_operator(n: int, weights: np.ndarray, f: int) -> np.ndarray:
    """(n, max(1, n // f)) float32 matrix carrying one axis of n cells through a convolution with the
    symmetric weights, renormalised to the weights inside the axis, and then through means of f-cell
    blocks (cells past the end read 0)."""
    weights = np.asarray(weights, dtype=np.float64)
    r = (len(weights) - 1) // 2
    m = max(1, n // f)
    op = np.zeros((n, m))
    for j in range(m):
        for i in range(j * f, min(n, j * f + f)):
            lo, hi = max(0, i - r), min(n, i + r + 1)
            w = weights[lo - i + r: hi - i + r]
            op[lo:hi, j] += w / (w.sum() * f)
    return op.astype(np.float32)


@nb.njit(**_JIT)
def _apply_leading(src, axis, op):
    """src (3D, float32) with axis 0 or 1 carried through the banded matrix op (n, m)."""
    n, m = op.shape
    mx = m if axis == 0 else src.shape[0]
    my = m if axis == 1 else src.shape[1]
    mz = src.shape[2]
    out = np.zeros((mx, my, mz), dtype=np.float32)
    for j in range(m):
        for k in range(n):
            w = op[k, j]
            if w == 0.0:
                continue
            if axis == 0:
                for y in range(my):
                    for z in range(mz):
                        out[j, y, z] += w * src[k, y, z]
            else:
                for x in range(mx):
                    for z in range(mz):
                        out[x, j, z] += w * src[x, k, z]
    return out


def smooth(img: np.ndarray, weights: np.ndarray, f: int = 1) -> np.ndarray:
    """img convolved with the symmetric weights along each axis (near the borders renormalised to the
    weights inside: outside is no evidence, not zero intensity), then means of f^3 blocks. The last
    axis, short and contiguous, is one matrix product; the others are banded sums of whole slabs."""
    img = np.asarray(img, dtype=np.float32)
    for axis in range(3):
        op = axis_operator(img.shape[axis], weights, f)
        img = img @ op if axis == 2 else _apply_leading(img, axis, op)
    return img


def gaussian_weights(radius: int, sigma: float) -> np.ndarray:
    """Gaussian of standard deviation sigma cells, truncated at radius cells."""
    x = np.arange(-radius, radius + 1, dtype=np.float64)
    return np.exp(-0.5 * (x / sigma) ** 2)


def gaussian(img: np.ndarray, radius: int = 3, sigma: float = 1.0, iterations: int = 1) -> np.ndarray:
    """Separable Gaussian smoothing truncated at radius cells; near the borders the weights inside
    the image are renormalised (outside is no evidence, not zero intensity)."""
    img = np.asarray(img, dtype=np.float32)
    for _ in range(iterations):
        img = smooth(img, gaussian_weights(radius, sigma))
    return img


def downsample(img: np.ndarray, known: np.ndarray, radius: int = 1):
    """Block means with factor 2*radius per axis (eq. 34); a block is known when any of its cells is.
    Radius 0 leaves the image as it is."""
    f = max(1, 2 * radius)
    return smooth(img, np.ones(1), f), smooth(known, np.ones(1), f) > 0


def preprocess(grid: OccupancyGrid, params: MergeParams) -> FeatureImage:
    """§8.1 in order: dilate, erode, Gaussian, downsample; returns the image features are found on.
    Morphology runs on the int8 cells (intensity is monotonic in occupancy, so max and min commute
    with it), and the last Gaussian pass is fused with the downsampling (both are separable)."""
    closed = erode(dilate(grid.cells, params.dilate_radius, params.dilate_iterations),
                   params.erode_radius, params.erode_iterations)
    img = gaussian(intensity(closed), params.gaussian_radius, params.gaussian_sigma,
                   params.gaussian_iterations - 1)
    f = max(1, 2 * params.downsample_radius)
    weights = gaussian_weights(params.gaussian_radius, params.gaussian_sigma) if params.gaussian_iterations \
        else np.ones(1)
    img = smooth(img, weights, f)
    known = smooth(grid.cells != -1, np.ones(1), f) > 0
    origin = (grid.offset + (f - 1) / 2.0) * grid.resolution
    return FeatureImage(img, known, origin, f * grid.resolution)


@nb.njit(**_JIT)
def _speckles(cells, threshold, max_occupied):
    """(mask of occupied cells with at most max_occupied occupied neighbours (of 26) and more free
    neighbours than unknown ones, how many there are, how many cells are occupied)."""
    mx, my, mz = cells.shape
    out = np.zeros(cells.shape, dtype=np.bool_)
    speckles = occupied = 0
    for x in range(mx):
        for y in range(my):
            for z in range(mz):
                if cells[x, y, z] < threshold:
                    continue
                occupied += 1
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
                speckles += out[x, y, z]
    return out, speckles, occupied


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
    drop, speckles, occupied = _speckles(grid.cells, params.occupied_threshold, params.despeckle_max_occupied)
    if not speckles or speckles < params.despeckle_min_share * occupied:
        return grid
    cells = grid.cells.copy()
    for _ in range(params.despeckle_passes):
        cells[drop] = -1
        drop, speckles, _ = _speckles(cells, params.occupied_threshold, params.despeckle_max_occupied)
        if not speckles:
            break
    return OccupancyGrid(cells, grid.resolution, grid.offset)

"""The 3D dynamic occupancy grid (thesis §6.1–6.2, notes §2).

Cells live in a box of integer *keys*: key k is the cell whose centre is at k * resolution
metres in the map frame, so the map origin is the centre of key (0, 0, 0). The array element
[0, 0, 0] holds key ``offset``; storage is row-major, flat index i = z + m_z * (y + m_y * x).
When something touches a key outside the box (plus the safety margin m_sm), the box grows:
symmetrically in x and y by a fixed step, so the start point stays at the horizontal centre,
and by layers in z on the side that needs them.
"""

from dataclasses import dataclass

import numpy as np

from . import kernels
from .cells import CELL_DTYPE, OCCUPIED_THRESHOLD, UNKNOWN


class GridTooLarge(ValueError):
    """Raised instead of allocating a grid beyond GrowthPolicy.max_cells."""


@dataclass(frozen=True)
class GrowthPolicy:
    """How the grid grows (thesis §6.1, Figure 25)."""

    margin: int = 5
    """m_sm: cells kept free of accesses along every border."""
    horizontal_step: int = 20
    """Cells added on *each* side of x and y whenever x or y must grow."""
    vertical_step: int = 5
    """Layers added at a time on the z side that needs them."""
    max_cells: int = 400_000_000
    """Growth past this many cells raises GridTooLarge (bounded memory, hostile poses)."""

    def __post_init__(self):
        if self.margin < 0 or self.horizontal_step < 1 or self.vertical_step < 1 or self.max_cells < 1:
            raise ValueError(f"invalid growth policy {self}")


@dataclass(frozen=True)
class CellCounts:
    unknown: int
    inaccessible: int
    free: int
    occupied: int

    @property
    def known(self) -> int:
        return self.inaccessible + self.free + self.occupied

    @property
    def total(self) -> int:
        return self.known + self.unknown


class OccupancyGrid:
    """int8 occupancy cells of a growing box of the map frame; see the module docstring."""

    __slots__ = ("_cells", "resolution", "_offset", "growth")

    def __init__(self, cells: np.ndarray, resolution: float, offset=(0, 0, 0),
                 growth: GrowthPolicy = GrowthPolicy()):
        cells = np.asarray(cells)
        if cells.ndim != 3 or cells.dtype != CELL_DTYPE:
            raise ValueError(f"cells must be a 3D int8 array, got {cells.ndim}D {cells.dtype}")
        if not (np.isfinite(resolution) and 1e-4 <= resolution <= 100.0):
            raise ValueError(f"resolution must be in [1e-4, 100] m, got {resolution}")
        self._cells = np.ascontiguousarray(cells)
        self.resolution = float(resolution)
        self._offset = np.array(offset, dtype=np.int64).reshape(3)
        self.growth = growth

    @classmethod
    def empty(cls, shape=(40, 40, 20), resolution: float = 0.1,
              growth: GrowthPolicy = GrowthPolicy()) -> "OccupancyGrid":
        """An all-unknown grid of `shape` cells, centred on the map origin."""
        shape = tuple(int(s) for s in shape)
        if len(shape) != 3 or min(shape) < 1:
            raise ValueError(f"shape must be three positive sizes, got {shape}")
        if int(np.prod(shape)) > growth.max_cells:
            raise GridTooLarge(f"{shape} exceeds {growth.max_cells} cells")
        offset = [-(s // 2) for s in shape]
        return cls(np.full(shape, UNKNOWN, dtype=CELL_DTYPE), resolution, offset, growth)

    # ----------------------------------------------------------------------------- geometry
    @property
    def cells(self) -> np.ndarray:
        """The cells as a (m_x, m_y, m_z) array, indexed [x, y, z] in array coordinates."""
        return self._cells

    @property
    def flat(self) -> np.ndarray:
        """The row-major 1D storage of the thesis (a view)."""
        return self._cells.reshape(-1)

    @property
    def shape(self) -> tuple[int, int, int]:
        return self._cells.shape

    @property
    def size(self) -> int:
        """N = m_x * m_y * m_z (thesis eq. 16)."""
        return self._cells.size

    @property
    def offset(self) -> np.ndarray:
        """Key of array element [0, 0, 0] (a copy)."""
        return self._offset.copy()

    def flat_index(self, x, y, z):
        """Thesis eq. 15: i = z + m_z * (y + m_y * x), for array coordinates."""
        _, my, mz = self.shape
        return z + mz * (y + my * x)

    def keys_of(self, points_m) -> np.ndarray:
        """Keys of the cells holding points given in metres (…, 3)."""
        return np.floor(np.asarray(points_m, dtype=np.float64) / self.resolution + 0.5).astype(np.int64)

    def centres_of(self, keys) -> np.ndarray:
        """Map-frame centres (metres) of cells given by key."""
        return np.asarray(keys, dtype=np.float64) * self.resolution

    def key_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Inclusive key range (lo, hi) the grid covers."""
        return self._offset.copy(), self._offset + np.array(self.shape) - 1

    def bounds_m(self) -> tuple[np.ndarray, np.ndarray]:
        """Map-frame box (min corner, max corner) in metres covered by the grid."""
        lo, hi = self.key_bounds()
        return (lo - 0.5) * self.resolution, (hi + 0.5) * self.resolution

    def contains(self, keys) -> np.ndarray:
        keys = np.asarray(keys)
        lo, hi = self.key_bounds()
        return np.all((keys >= lo) & (keys <= hi), axis=-1)

    # ----------------------------------------------------------------------------- access
    def values_at_keys(self, keys) -> np.ndarray:
        """Cell values for keys (…, 3); UNKNOWN outside the grid. Never grows."""
        keys = np.asarray(keys, dtype=np.int64)
        out = np.full(keys.shape[:-1], UNKNOWN, dtype=CELL_DTYPE)
        inside = self.contains(keys)
        a = keys[inside] - self._offset
        out[inside] = self._cells[a[:, 0], a[:, 1], a[:, 2]]
        return out

    def values_at(self, points_m) -> np.ndarray:
        return self.values_at_keys(self.keys_of(points_m))

    def set_keys(self, keys, values) -> None:
        """Write values at keys (…, 3), growing the grid first if needed."""
        keys = np.asarray(keys, dtype=np.int64).reshape(-1, 3)
        if len(keys) == 0:
            return
        self.ensure(keys.min(axis=0), keys.max(axis=0))
        a = keys - self._offset
        self._cells[a[:, 0], a[:, 1], a[:, 2]] = values

    def block(self, lo_key, hi_key) -> np.ndarray:
        """Writable view of the inclusive key box [lo_key, hi_key], which must be inside."""
        lo = np.asarray(lo_key, dtype=np.int64) - self._offset
        hi = np.asarray(hi_key, dtype=np.int64) - self._offset
        if np.any(lo < 0) or np.any(hi >= self.shape) or np.any(hi < lo):
            raise IndexError(f"block {lo_key}..{hi_key} is not inside the grid")
        return self._cells[lo[0]:hi[0] + 1, lo[1]:hi[1] + 1, lo[2]:hi[2] + 1]

    # ----------------------------------------------------------------------------- growth
    def ensure(self, lo_key, hi_key) -> bool:
        """Grow so that keys lo..hi plus the safety margin fit; True if the grid grew.

        x and y grow together on both sides by whole horizontal steps (the start point stays
        at the horizontal centre); z grows by whole vertical steps on the side that needs it.
        """
        lo_key = np.asarray(lo_key, dtype=np.int64)
        hi_key = np.asarray(hi_key, dtype=np.int64)
        m = self.growth.margin
        cur_lo, cur_hi = self.key_bounds()
        need_lo = np.maximum(cur_lo - (lo_key - m), 0)
        need_hi = np.maximum((hi_key + m) - cur_hi, 0)
        if not (need_lo.any() or need_hi.any()):
            return False
        h_need = max(int(need_lo[:2].max()), int(need_hi[:2].max()))
        h = -(-h_need // self.growth.horizontal_step) * self.growth.horizontal_step
        vs = self.growth.vertical_step
        z_lo = -(-int(need_lo[2]) // vs) * vs
        z_hi = -(-int(need_hi[2]) // vs) * vs
        self._resize(np.array([h, h, z_lo]), np.array([h, h, z_hi]))
        return True

    def _resize(self, add_lo: np.ndarray, add_hi: np.ndarray) -> None:
        new_shape = tuple(int(s) for s in np.array(self.shape) + add_lo + add_hi)
        n = int(np.prod(np.array(new_shape, dtype=np.int64)))
        if n > self.growth.max_cells:
            raise GridTooLarge(f"growing to {new_shape} ({n} cells) exceeds the limit of "
                               f"{self.growth.max_cells} cells")
        new = np.full(new_shape, UNKNOWN, dtype=CELL_DTYPE)
        mx, my, mz = self.shape
        new[add_lo[0]:add_lo[0] + mx, add_lo[1]:add_lo[1] + my, add_lo[2]:add_lo[2] + mz] = self._cells
        self._cells = new
        self._offset = self._offset - add_lo

    # ----------------------------------------------------------------------------- whole grid
    def copy(self) -> "OccupancyGrid":
        return OccupancyGrid(self._cells.copy(), self.resolution, self._offset, self.growth)

    def known_key_bounds(self):
        """Inclusive key range of the known cells, or None when nothing is known."""
        lo, hi = kernels.known_bounds(self._cells)
        if lo[0] > hi[0]:
            return None
        return lo + self._offset, hi + self._offset

    def shrunk(self, pad: int = 0) -> "OccupancyGrid":
        """A copy cropped to the bounding box of known cells (plus `pad` cells of unknown)."""
        bounds = self.known_key_bounds()
        if bounds is None:
            return OccupancyGrid.empty((1, 1, 1), self.resolution, self.growth)
        lo, hi = bounds[0] - pad, bounds[1] + pad
        out = OccupancyGrid(np.full(tuple(hi - lo + 1), UNKNOWN, dtype=CELL_DTYPE),
                            self.resolution, lo, self.growth)
        out.paste(self)
        return out

    def paste(self, other: "OccupancyGrid") -> None:
        """Overwrite the overlap of this grid with `other`'s cells (same resolution)."""
        self._check_same_resolution(other)
        box = self._overlap(other)
        if box is not None:
            lo, hi = box
            self.block(lo, hi)[...] = other.block(lo, hi)

    def _overlap(self, other: "OccupancyGrid"):
        a_lo, a_hi = self.key_bounds()
        b_lo, b_hi = other.key_bounds()
        lo, hi = np.maximum(a_lo, b_lo), np.minimum(a_hi, b_hi)
        return None if np.any(hi < lo) else (lo, hi)

    def _check_same_resolution(self, other: "OccupancyGrid") -> None:
        if abs(other.resolution - self.resolution) > 1e-9 * self.resolution:
            raise ValueError(f"resolutions differ: {self.resolution} m vs {other.resolution} m")

    def counts(self, threshold: int = OCCUPIED_THRESHOLD) -> CellCounts:
        return CellCounts(*(int(c) for c in kernels.count_classes(self.flat, threshold)))

    def same_cells(self, other: "OccupancyGrid") -> bool:
        """True when both grids hold the same value for every key (unknown outside either)."""
        if abs(other.resolution - self.resolution) > 1e-9 * self.resolution:
            return False
        a, b = self.shrunk(), other.shrunk()
        if a.known_key_bounds() is None or b.known_key_bounds() is None:
            return a.known_key_bounds() is None and b.known_key_bounds() is None
        return bool(np.array_equal(a.offset, b.offset) and np.array_equal(a.cells, b.cells))

    def __repr__(self) -> str:
        return (f"OccupancyGrid(shape={self.shape}, resolution={self.resolution}, "
                f"offset={tuple(int(v) for v in self._offset)})")

"""The Mapper: owns a vehicle's local grid and integrates depth frames into it (thesis §6.3)."""

import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace

import numpy as np

from ..grid import OCCUPIED_THRESHOLD, GrowthPolicy, OccupancyGrid
from . import raycast
from .sensor import FrameRejected, Intrinsics, Pose, check_depth

MAX_SCRATCH_CELLS = 64_000_000
"""Largest per-frame box (cells) a frame may touch; bounds memory whatever the range setting."""


_TRAVERSALS = {"bresenham": raycast.TRAVERSAL_BRESENHAM, "exact": raycast.TRAVERSAL_EXACT}
BEYOND_MAX_RANGE = ("clear", "drop")
FARTHEST_READING_M = 1000.0
"""A depth beyond this is no camera's reading but a corrupt one: skipped, never a ray."""


@dataclass(frozen=True)
class MapperConfig:
    """Sensor model and HIMM parameters (thesis §6.3; defaults from docs/method.md §3)."""

    resolution: float = 0.10
    """m_r, metres per cell."""
    min_range: float = 0.2
    max_range: float = 5.0
    """Rays are cut at this range: the cells up to it are misses, the cut end is no hit."""
    beyond_max_range: str = "clear"
    """A pixel reading farther than max_range: "clear" casts its ray cut at max range, clearing
    free space and marking no hit (OctoMap's maxrange); "drop" skips the pixel, for a camera
    whose far readings are too noisy to trust even as free space."""
    hit_increment: int = 10
    """m_I+: added to cells in the hit region."""
    miss_decrement: int = 15
    """m_I-: taken from cells the ray passes through."""
    hit_depth: float = 0.0
    """m_d, metres: cells entered within this distance of the measured point count as hits."""
    graze_deg: float = 20.0
    """A ray running within this angle of the level surface in an occupied cell (a floor, ceiling or
    table top: the plane across the cell's free side) does not clear it: it passes through the free
    part of a cell that holds a floor seen edge-on. Walls are cleared as before. 0: every ray clears
    every cell it passes, as HIMM reads."""
    traversal: str = "bresenham"
    """Ray traversal: "bresenham" (thesis, one cell per major-axis step) or "exact" (every cell
    the ray crosses)."""
    per_frame_dedup: bool = True
    """Each cell updated at most once per frame (hit wins). False: the thesis' per-ray updates."""
    gap_fill: bool = True
    threads: int = 1
    """Ray-tracing threads (mark mode only); results are identical for any count."""
    growth: GrowthPolicy = field(default_factory=GrowthPolicy)

    @property
    def far_limit(self) -> float:
        """Farthest depth reading that makes a ray (longer ones are cut at max_range)."""
        return FARTHEST_READING_M if self.beyond_max_range == "clear" else self.max_range

    def __post_init__(self):
        problems = []
        if not (0.01 <= self.resolution <= 10):
            problems.append(f"resolution {self.resolution} m outside 0.01..10")
        if not (0 <= self.min_range < self.max_range <= 100):
            problems.append(f"range {self.min_range}..{self.max_range} m must satisfy 0 <= min < max <= 100")
        if not (1 <= self.hit_increment <= 100 and 1 <= self.miss_decrement <= 100):
            problems.append("hit_increment and miss_decrement must be in 1..100")
        if not (0 <= self.hit_depth <= 10):
            problems.append(f"hit_depth {self.hit_depth} m outside 0..10")
        if not (0 <= self.graze_deg <= 60):
            problems.append(f"graze_deg {self.graze_deg} outside 0..60")
        if self.beyond_max_range not in BEYOND_MAX_RANGE:
            problems.append(f"beyond_max_range {self.beyond_max_range!r} is not one of "
                            f"{list(BEYOND_MAX_RANGE)}")
        if self.traversal not in _TRAVERSALS:
            problems.append(f"traversal {self.traversal!r} is not one of {sorted(_TRAVERSALS)}")
        if not (1 <= self.threads <= 64):
            problems.append(f"threads {self.threads} outside 1..64")
        if problems:
            raise ValueError("; ".join(problems))


@dataclass(frozen=True)
class IntegrationStats:
    """What one frame did to the grid."""

    rays: int
    invalid_pixels: int
    truncated_rays: int
    cells_updated: int
    """Cells that got an update (per-ray mode: cell visits, a cell counting once per ray)."""
    hits: int
    gaps_filled: int
    grew: bool
    seconds: float


@dataclass
class MapperTotals:
    frames: int = 0
    frames_rejected: int = 0
    rays: int = 0
    invalid_pixels: int = 0
    truncated_rays: int = 0
    last_stamp: float | None = None
    reject_reasons: dict = field(default_factory=dict)


class Mapper:
    """Integrates (depth, intrinsics, camera pose) frames into one occupancy grid.

    The grid is guarded by `lock`; readers that need a consistent view call `snapshot()`.
    """

    def __init__(self, config: MapperConfig = MapperConfig(), grid: OccupancyGrid | None = None):
        self.config = config
        if grid is not None and abs(grid.resolution - config.resolution) > 1e-9:
            raise ValueError(f"grid resolution {grid.resolution} differs from config {config.resolution}")
        self.grid = grid if grid is not None else OccupancyGrid.empty(
            (40, 40, 20), config.resolution, config.growth)
        self.lock = threading.Lock()
        self.totals = MapperTotals()
        self.version = 0
        """Bumped by every frame that changed the grid."""
        self._pool = ThreadPoolExecutor(config.threads, "coopd-ray") if config.threads > 1 else None
        self._slopes_for: Intrinsics | None = None
        self._slopes = (np.zeros(0), np.zeros(0))
        self._graze_sin = float(np.sin(np.radians(config.graze_deg)))

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True)
            self._pool = None

    def snapshot(self) -> tuple[OccupancyGrid, int]:
        """A private copy of the grid and the version it reflects."""
        with self.lock:
            return self.grid.copy(), self.version

    def integrate(self, depth: np.ndarray, intrinsics: Intrinsics, camera_pose: Pose,
                  stamp: float | None = None) -> IntegrationStats:
        """Ray-cast one frame into the grid. Raises FrameRejected (grid untouched) on bad input;
        invalid pixels are skipped and counted."""
        t0 = time.perf_counter()
        try:
            depth = check_depth(depth, intrinsics)
            if not isinstance(camera_pose, Pose):
                raise FrameRejected("camera pose must be a Pose")
        except FrameRejected as e:
            self._count_reject(e)
            raise
        with self.lock:
            stats = self._integrate_locked(depth, intrinsics, camera_pose, t0)
            self.totals.frames += 1
            self.totals.rays += stats.rays
            self.totals.invalid_pixels += stats.invalid_pixels
            self.totals.truncated_rays += stats.truncated_rays
            self.totals.last_stamp = stamp
            if stats.cells_updated:
                self.version += 1
        return stats

    def _count_reject(self, e: Exception) -> None:
        self.totals.frames_rejected += 1
        reason = str(e).split(":")[0][:60]
        self.totals.reject_reasons[reason] = self.totals.reject_reasons.get(reason, 0) + 1

    def _integrate_locked(self, depth, intrinsics, pose, t0) -> IntegrationStats:
        cfg = self.config
        if self._slopes_for != intrinsics:
            self._slopes = intrinsics.ray_slopes()
            self._slopes_for = intrinsics
        sx, sy = self._slopes
        scale = float(intrinsics.depth_scale) if depth.dtype == np.uint16 else 1.0
        rot = pose.rotation()
        origin = pose.position
        lo_m, hi_m, valid = raycast.endpoint_bounds(depth, scale, sx, sy, rot, origin,
                                                    cfg.min_range, cfg.max_range, cfg.far_limit)
        if valid == 0:
            return IntegrationStats(0, depth.size, 0, 0, 0, 0, False, time.perf_counter() - t0)
        grid = self.grid
        lo_key, hi_key = grid.keys_of(lo_m), grid.keys_of(hi_m)
        box_shape = hi_key - lo_key + 1
        if int(np.prod(box_shape)) > MAX_SCRATCH_CELLS:
            e = FrameRejected(f"frame box {tuple(box_shape)} exceeds {MAX_SCRATCH_CELLS} cells")
            self._count_reject(e)
            raise e
        try:
            grew = grid.ensure(lo_key, hi_key)
        except ValueError as e:
            self._count_reject(e)
            raise FrameRejected(f"grid cannot grow to hold this frame: {e}") from e
        inv_res = 1.0 / grid.resolution
        box_lo = lo_key - grid.offset
        counts = np.zeros((max(cfg.threads, 1), raycast.N_COUNTS), dtype=np.int64)
        inc, dec = cfg.hit_increment, cfg.miss_decrement
        if cfg.per_frame_dedup:
            # Origin in continuous coordinates of the frame box (cell k spans [k-0.5, k+0.5)).
            origin_c = origin * inv_res - lo_key + 0.5
            updated, hits = self._trace_marked(depth, scale, sx, sy, rot, origin_c, inv_res,
                                               box_lo, box_shape, counts)
        else:
            origin_c = origin * inv_res - grid.offset + 0.5
            shape = np.array(grid.shape, dtype=np.int64)
            raycast.trace_rows(depth, scale, sx, sy, 0, depth.shape[0], rot, origin_c, inv_res,
                               cfg.min_range, cfg.max_range, cfg.far_limit, cfg.hit_depth, shape, grid.flat,
                               raycast.MODE_PER_RAY, _TRAVERSALS[cfg.traversal], inc, dec, grid.cells,
                               np.zeros(3, dtype=np.int64), self._graze_sin, counts[0])
            updated = int(counts[0, raycast.COUNT_VISITS])
            hits = int(counts[0, raycast.COUNT_RAYS] - counts[0, raycast.COUNT_TRUNCATED])
        filled = 0
        if cfg.gap_fill:
            filled = int(raycast.gap_fill(grid.cells, box_lo, box_lo + box_shape - 1, OCCUPIED_THRESHOLD))
        total = counts.sum(axis=0)
        rays = int(total[raycast.COUNT_RAYS])
        return IntegrationStats(
            rays=rays,
            invalid_pixels=int(total[raycast.COUNT_INVALID]),
            truncated_rays=int(total[raycast.COUNT_TRUNCATED]),
            cells_updated=int(updated),
            hits=int(hits),
            gaps_filled=filled,
            grew=grew,
            seconds=time.perf_counter() - t0,
        )

    def _trace_marked(self, depth, scale, sx, sy, rot, origin_c, inv_res, box_lo, box_shape, counts):
        cfg = self.config
        n_threads = cfg.threads
        marks = np.zeros((n_threads, int(np.prod(box_shape))), dtype=np.uint8)
        rows = np.linspace(0, depth.shape[0], n_threads + 1).astype(np.int64)
        shape = box_shape.astype(np.int64)

        def trace(k):
            raycast.trace_rows(depth, scale, sx, sy, rows[k], rows[k + 1], rot, origin_c, inv_res,
                               cfg.min_range, cfg.max_range, cfg.far_limit, cfg.hit_depth, shape,
                               marks[k], raycast.MODE_MARK, _TRAVERSALS[cfg.traversal], 0, 0, self.grid.cells,
                               box_lo, self._graze_sin, counts[k])

        xs = np.linspace(0, int(box_shape[0]), n_threads + 1).astype(np.int64)

        def apply(k):
            return raycast.apply_marks(self.grid.cells, box_lo, marks, shape, xs[k], xs[k + 1],
                                       cfg.hit_increment, cfg.miss_decrement)

        if self._pool is None:
            trace(0)
            return apply(0)
        list(self._pool.map(trace, range(n_threads)))
        results = list(self._pool.map(apply, range(n_threads)))
        return sum(r[0] for r in results), sum(r[1] for r in results)


def load_kernels(config: MapperConfig | None = None) -> OccupancyGrid:
    """Load (or, on an empty numba cache, compile) the integration kernels by mapping one small
    frame into a throwaway grid, so that the first real frame is not delayed by seconds of JIT.
    Returns that grid (a few walls and free cells) for warming up what consumes maps."""
    m = Mapper(replace(config or MapperConfig(), threads=1))
    try:
        forward = Pose(np.zeros(3), np.array([0.5, -0.5, 0.5, -0.5]))
        m.integrate(np.full((24, 32), 2000, np.uint16), Intrinsics.from_fov(32, 24, 87.0), forward)
    finally:
        m.close()
    return m.grid

"""Re-anchoring the FC's new frame onto the map after a reboot or estimator reset moved it.

While FrameContinuity (coopd.vehicle.frame_continuity) holds mapping paused, the mapping thread hands
each frame here instead: it is ray-cast, with the pose of the FC's new (unanchored) frame, into a small
local map of its own. After a few frames that local map is registered against the own map around
where the hold-position guess puts it (the last pose before the break = the first one after), by the
merging pipeline's hinted registration: ICP from the guess, then the same validation a merge passes
(coopd.merging.hints.validate_hint). Accepted: the correction is set and mapping resumes in the map
frame, continuous. Refused: mapping stays paused with the reason; the local map keeps growing to the
next attempt (new headings add views that pin the frame down: a camera looking along a corridor sees
nothing that fixes the position along it, and such a fit is refused), and starts over after max_frames.

Bounded: the local map has its own cell cap, the own map is read only inside a box around the local
map, and one attempt costs one ICP and one validation on those small grids.
"""

from __future__ import annotations

import logging
import math
import time
from collections import Counter, deque
from dataclasses import dataclass, field, replace

import numpy as np

from ..geometry import apply, rotation_angle_deg, rotation_z
from ..grid import UNKNOWN, OccupancyGrid
from ..merging.hints import validate_hint
from ..merging.pair import MergeResult, PreparedMap, as_given, prepare
from ..merging.params import MergeParams, coopd_params
from ..merging.validation import agreement
from .association import pose_waiting
from .mapper import Mapper
from .sensor import CameraMount, FrameRejected, Pose

log = logging.getLogger("coopd.mapping")


def reanchor_params() -> MergeParams:
    """coopd's merge validation, scaled to a local map of a few frames: fewer agreeing cells needed
    (a few frames see a few hundred wall cells) and the overlap share measured on the cropped own
    map; the score threshold, which catches a shifted fit, stays."""
    return coopd_params().with_(min_agreement=150, min_overlap=0.1)


@dataclass(frozen=True)
class ReanchorConfig:
    """When to try, and how much to spend."""

    first_attempt_frames: int = 6
    """Frames integrated into the local map before the first attempt..."""
    attempt_every_frames: int = 6
    """...then an attempt after this many more (a new heading may show what pins the frame down), but
    never sooner after the last than it took (at most half of the mapping thread's time)..."""
    max_frames: int = 240
    """...until the local map holds this many frames: then it starts over."""
    max_local_cells: int = 8_000_000
    """Cell cap of the local map (int8 cells: 8 MB)."""
    margin_m: float = 2.0
    """The own map is read in the local map's box (placed by the guess) grown by this margin."""
    spread_m: float = 0.4
    """ICP also starts this far beside the guess, along x and y (four more starts)."""
    slide_m: float = 0.3
    min_slide_drop: float = 0.03
    """A fit moved slide_m horizontally, in any of 8 directions, must score at least this much lower
    (validation score): otherwise the views do not pin the frame down along that direction (a wall or
    shelf row seen along its length) and ICP may slide anywhere along it."""
    params: MergeParams = field(default_factory=reanchor_params)


def gravity_aligned(transform: np.ndarray, pivot: np.ndarray) -> np.ndarray:
    """The transform with its rotation reduced to the turn about z (both FC frames are levelled by
    gravity: a tilt ICP found is noise), keeping where it puts `pivot` (the local map's centre)."""
    rot = transform[:3, :3]
    out = np.eye(4)
    out[:3, :3] = rotation_z(math.atan2(rot[1, 0] - rot[0, 1], rot[0, 0] + rot[1, 1]))
    out[:3, 3] = rot @ pivot + transform[:3, 3] - out[:3, :3] @ pivot
    return out


def starts(guess: np.ndarray, spread_m: float) -> list[np.ndarray]:
    """The hold guess and four starts spread_m beside it: the vehicle may have moved off its hold
    position during the gap, and ICP from one start can slide into a neighbouring fit along repeated
    structure (shelves, a corridor); the best-validated fit of all wins."""
    out = [guess]
    for dx, dy in ((spread_m, 0.0), (-spread_m, 0.0), (0.0, spread_m), (0.0, -spread_m)):
        s = guess.copy()
        s[:2, 3] += (dx, dy)
        out.append(s)
    return out


def register(own: PreparedMap, local: PreparedMap, guess: np.ndarray, params: MergeParams,
             spread_m: float) -> MergeResult:
    """The local map's fit on the own map (validate_hint: ICP then a merge's validation, refused if ICP
    moved it far) from the guess, or when that is refused the best-validated one over the other
    starts; when none is accepted, the best refused one. The guess itself is kept when it validates
    and scores at least as well: ICP maximises the cells it pairs, and on a local map of a few frames
    it can move a near-exact guess 0.3 m and 2-4 deg to a fit with more paired cells and more
    conflicts (a score of 0.965 against the guess's 0.973)."""
    held = as_given(own, local, guess, params, method="hold guess")
    first = validate_hint(own, local, guess, params)
    if not first.accepted:
        results = [first] + [validate_hint(own, local, s, params) for s in starts(guess, spread_m)[1:]]
        first = max(results, key=lambda r: (r.accepted, r.score, r.agreement))
    return held if held.accepted and (not first.accepted or held.score >= first.score) else first


def slide_direction(own: PreparedMap, local: PreparedMap, transform: np.ndarray, slide_m: float,
                    min_drop: float) -> tuple[float, float] | None:
    """(heading deg, score there) of a horizontal direction along which the fit can slide slide_m
    losing less than min_drop of its validation score, or None when every direction is pinned down."""
    base = agreement(own.summary, local.summary, transform).score
    for heading in range(0, 360, 45):
        moved = transform.copy()
        a = math.radians(heading)
        moved[:2, 3] += slide_m * np.array([math.cos(a), math.sin(a)])
        score = agreement(own.summary, local.summary, moved).score
        if base - score < min_drop:
            return float(heading), score
    return None


def own_map_around(mapper: Mapper, lo_m: np.ndarray, hi_m: np.ndarray) -> OccupancyGrid:
    """A copy of the own map inside the box [lo_m, hi_m] (unknown where the map does not reach)."""
    res = mapper.config.resolution
    lo = np.floor(lo_m / res).astype(np.int64)
    hi = np.ceil(hi_m / res).astype(np.int64)
    out = OccupancyGrid(np.full(tuple(hi - lo + 1), UNKNOWN, dtype=np.int8), res, lo)
    with mapper.lock:
        out.paste(mapper.grid)
    return out


def placed_box(grid: OccupancyGrid, guess: np.ndarray, margin_m: float) -> tuple[np.ndarray, np.ndarray]:
    """The map-frame box holding the grid's known cells carried by guess, grown by margin_m."""
    bounds = grid.known_key_bounds()
    lo, hi = (grid.bounds_m() if bounds is None else
              (grid.centres_of(bounds[0]) - grid.resolution, grid.centres_of(bounds[1]) + grid.resolution))
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    moved = apply(guess, corners)
    return moved.min(axis=0) - margin_m, moved.max(axis=0) + margin_m


class FrameReanchor:
    """Owns the local map of the unanchored frame; offer() runs on the mapping thread."""

    def __init__(self, frames, mapper: Mapper, mount: CameraMount, config: ReanchorConfig = ReanchorConfig(),
                 pose_wait_s: float = 0.1):
        self.frames = frames
        self.pose_wait_s = pose_wait_s
        """How long a frame newer than the newest pose of the new frame waits for it (as in association)."""
        self.mapper = mapper
        self.mount = mount
        self.config = config
        self.counters: Counter = Counter()
        self.last_result: dict | None = None
        self.refusals: deque[str] = deque(maxlen=4)
        """The last few refusal reasons (status)."""
        self._epoch: int | None = None
        self._local: Mapper | None = None
        self._integrated = 0
        self._last_attempt = (0, -math.inf, 0.0)
        """(frames, monotonic end, duration) of the last attempt."""

    def offer(self, frame) -> None:
        """A frame taken while mapping is paused for the frame: into the local map, then maybe an attempt."""
        anchor = self.frames.pending_anchor()
        if anchor is None:
            self.counters["no_new_pose_yet"] += 1
            return
        epoch, guess = anchor
        if epoch != self._epoch:
            self._restart(epoch)
        try:
            sample = pose_waiting(self.frames.raw_pose_at, frame.t_fc, self.pose_wait_s)
            camera = self.mount.camera_pose(Pose(sample.position, sample.quaternion))
            self._local.integrate(frame.depth, frame.intrinsics, camera, frame.t_fc)
        except LookupError as e:
            self.counters["skipped_" + getattr(e, "reason", "no_pose")] += 1
            return
        except (FrameRejected, ValueError):
            self.counters["skipped_rejected"] += 1
            return
        self._integrated += 1
        self.counters["frames"] += 1
        if self._attempt_due(time.monotonic()):
            self._attempt(epoch, guess)
        if self._local is not None and self._integrated >= self.config.max_frames:
            self._restart(epoch)

    def _attempt_due(self, now: float) -> bool:
        """Enough frames for the first attempt, or enough new ones and time since the last."""
        cfg, (frames, end, took) = self.config, self._last_attempt
        if frames == 0:
            return self._integrated >= cfg.first_attempt_frames
        return self._integrated - frames >= cfg.attempt_every_frames and now - end >= took

    def _restart(self, epoch: int) -> None:
        """A new, empty local map (a new break, or the attempts on the last one ran out)."""
        cfg = self.mapper.config
        growth = replace(cfg.growth, max_cells=self.config.max_local_cells)
        self._local = Mapper(replace(cfg, growth=growth, threads=1))
        self._epoch, self._integrated = epoch, 0
        self._last_attempt = (0, -math.inf, 0.0)

    def _attempt(self, epoch: int, guess: np.ndarray) -> None:
        """Register the local map on the own map from the guess; anchor the frame if it validates."""
        t0 = time.perf_counter()
        self.counters["attempts"] += 1
        local = self._local.grid.shrunk(pad=1)
        own = own_map_around(self.mapper, *placed_box(local, guess, self.config.margin_m))
        params = self.config.params
        own_p, local_p = prepare(own, params, lazy=True), prepare(local, params, lazy=True)
        result = register(own_p, local_p, guess, params, self.config.spread_m)
        lo, hi = local.bounds_m()
        result = replace(result, transform=gravity_aligned(result.transform, (lo + hi) / 2))
        if result.accepted:
            slide = slide_direction(own_p, local_p, result.transform, self.config.slide_m,
                                    self.config.min_slide_drop)
            if slide is not None:
                result = replace(result, accepted=False, reason=(
                    f"the views do not pin the frame down: sliding {self.config.slide_m:.1f} m towards "
                    f"{slide[0]:.0f} deg still scores {slide[1]:.3f}"))
        moved = (float(np.linalg.norm(result.transform[:3, 3] - guess[:3, 3])),
                 rotation_angle_deg(guess[:3, :3].T @ result.transform[:3, :3]))
        elapsed = time.perf_counter() - t0
        self._last_attempt = (self._integrated, time.monotonic(), elapsed)
        self.last_result = {"accepted": result.accepted, "reason": result.reason,
                            "guess_shift_m": [round(float(v), 3) for v in guess[:3, 3]],
                            "score": round(result.score, 4), "agreeing_cells": result.agreement,
                            "overlap": round(result.overlap, 3),
                            "moved_from_guess_m": round(moved[0], 3),
                            "moved_from_guess_deg": round(moved[1], 2), "frames": self._integrated,
                            "seconds": round(elapsed, 3)}
        if result.accepted:
            detail = (f"{self._integrated} frames registered on the map in {elapsed:.2f} s: score "
                      f"{result.score:.3f}, {result.agreement} agreeing cells, {moved[0]:.2f} m / "
                      f"{moved[1]:.1f} deg from the hold-position guess")
            if self.frames.reanchor(epoch, result.transform, detail):
                self.counters["anchored"] += 1
                self._local, self._epoch = None, None
            return
        self.counters["refused"] += 1
        self.refusals.append(f"{result.reason} ({self._integrated} frames)")
        self.frames.refuse(f"{result.reason} after {self._integrated} frames")
        if self.counters["refused"] % 10 == 1:  # the first refusal, then one line in ten
            log.info("re-anchoring refused after %d frames (%.2f s): %s (%d refusals so far)",
                     self._integrated, elapsed, result.reason, self.counters["refused"])

    def status(self) -> dict:
        return {"frames": self._integrated, "counters": dict(self.counters), "last_result": self.last_result,
                "refusals": list(self.refusals)}

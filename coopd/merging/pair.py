"""Pairwise merging: hypotheses (global search and/or features), refinement, validation, decision."""

import time
from dataclasses import dataclass, field

import numpy as np

from ..geometry import invert, rotation_angle_deg
from ..grid import OccupancyGrid, resample, transform_grid
from . import yaw_search
from .features import MapFeatures, extract
from .level import level_transform
from .matching import match
from .mtm import euler_eq33
from .params import MergeParams, coopd_params
from .preprocess import despeckle
from .ransac import filter_correspondences
from .refine import OccupiedCells, field_fit, free_sides, icp
from .validation import Agreement, MapSummary, agreement, loosest_move, summarise

AMBIGUOUS = "ambiguous"
"""How the reason of a result refused for a close distinct runner-up begins (MergeResult.ambiguous)."""


@dataclass(frozen=True)
class MergeResult:
    """Outcome of merging b into a: transform maps points of b's frame into a's frame (metres)."""

    accepted: bool
    transform: np.ndarray
    inliers: int
    score: float
    agreement: int
    conflicts: int
    runner_up_score: float
    reason: str
    overlap: float = 0.0
    """Agreeing vertical-structure samples over all samples of both maps (0..1)."""
    timings: dict = field(default_factory=dict)
    method: str = "full"
    """How the transform was found: "full" (global search) or "hint:<source>" (a hint refined and
    validated, see hints.py); lets the daemon count the merge work it saved."""

    @property
    def ambiguous(self) -> bool:
        """Refused because a distinct hypothesis explains the maps about as well (min_margin)."""
        return not self.accepted and self.reason.startswith(AMBIGUOUS)

    def to_json(self) -> dict:
        """JSON-ready summary; euler_deg is (roll, pitch, yaw) by eq. 33."""
        roll, pitch, yaw = (float(np.degrees(v)) for v in euler_eq33(self.transform)[3:])
        return {"accepted": self.accepted, "transform": [[float(v) for v in row] for row in self.transform],
                "euler_deg": [round(roll, 4), round(pitch, 4), round(yaw, 4)],
                "inliers": self.inliers, "score": round(self.score, 4), "agreement": self.agreement,
                "conflicts": self.conflicts, "overlap": round(self.overlap, 4),
                "runner_up_score": round(self.runner_up_score, 4),
                "reason": self.reason, "method": self.method,
                "seconds": round(sum(self.timings.values()), 4),
                "timings": {k: round(v, 4) for k, v in self.timings.items()}}


@dataclass(frozen=True)
class Candidate:
    transform: np.ndarray
    inliers: int
    source: str


@dataclass
class PreparedMap:
    """Per-map work reused across merges (the global map is prepared again only when it changes)."""

    grid: OccupancyGrid
    summary: MapSummary
    occupied: OccupiedCells | None = None
    """The grid's occupied cells, refinement's target."""
    features: MapFeatures | None = None
    level: np.ndarray | None = None
    """Rotation levelling the map (level.py) and the levelled grid the yaw search runs on."""
    levelled: OccupancyGrid | None = None
    refine_points: tuple | None = None
    """((refine_max_points, threshold), points, free-side normals): what refinement moves when the map
    is b (_refine_points)."""


def prepare(grid: OccupancyGrid, params: MergeParams, timings: dict | None = None,
            lazy: bool = False) -> PreparedMap:
    """Summary for validation, a k-d tree for refinement and features when the variant uses them.
    lazy: only what judging a given transform needs; merge_prepared adds the rest when it searches."""
    tm = timings if timings is not None else {}
    t0 = time.perf_counter()
    grid = despeckle(grid, params)
    tm["despeckle"] = tm.get("despeckle", 0.0) + time.perf_counter() - t0
    t0 = time.perf_counter()
    summary = summarise(grid, params.occupied_threshold, params.validation_max_points,
                        params.validation_min_run(grid.resolution))
    occupied = OccupiedCells(grid.cells >= params.occupied_threshold, grid.offset, grid.resolution,
                             cells=grid.cells if params.refine_facing else None,
                             threshold=params.occupied_threshold)
    tm["summarise"] = tm.get("summarise", 0.0) + time.perf_counter() - t0
    p = PreparedMap(grid, summary, occupied, None, None, grid)
    if not lazy:
        complete(p, params, tm)
    return p


def complete(p: PreparedMap, params: MergeParams, tm: dict) -> None:
    """Add what the search and the feature stage need (levelling, features), once."""
    if params.search and params.level and p.level is None:
        t0 = time.perf_counter()
        p.level = level_transform(p.grid, params.occupied_threshold, params.level_max_tilt_deg)
        p.levelled = p.grid if np.allclose(p.level, np.eye(4)) else transform_grid(p.grid, p.level)
        tm["level"] = tm.get("level", 0.0) + time.perf_counter() - t0
    if params.hypotheses > 0 and p.features is None:
        p.features = extract(p.grid, params)
        for k, v in p.features.timings.items():
            tm[k] = tm.get(k, 0.0) + v


def _feature_candidates(a: PreparedMap, b: PreparedMap, params: MergeParams, tm: dict) -> list[Candidate]:
    """§8.6-8.8: match descriptors, filter by RANSAC, Kabsch on the inliers."""
    fa, fb = a.features, b.features
    if fa is None or fb is None:
        return []
    t0 = time.perf_counter()
    ia, ib, _ = match(fa.descriptors, fb.descriptors, params)
    tm["match"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    hyps = filter_correspondences(fb.points_m[ib], fa.points_m[ia], params.ransac_tolerance_cells * fa.cell_m,
                                  params)
    tm["ransac"] = time.perf_counter() - t0
    return [Candidate(h.transform, h.inlier_count, params.ransac_model) for h in hyps]


def _refine_points(b: PreparedMap, params: MergeParams) -> tuple[np.ndarray, np.ndarray]:
    """b's occupied cells thinned evenly to about refine_max_points, what refinement moves, and their
    free-side normals (refine.free_sides); made once per map."""
    key = (params.refine_max_points, params.occupied_threshold)
    if b.refine_points is None or b.refine_points[0] != key:
        src = np.ascontiguousarray(b.summary.occupied_m[:: max(1, len(b.summary.occupied_m)
                                                              // params.refine_max_points)])
        normals = free_sides(b.grid.cells, params.occupied_threshold, b.grid.offset, b.grid.resolution, src)
        b.refine_points = (key, src, normals)
    return b.refine_points[1], b.refine_points[2]


def _refined(a: PreparedMap, b: PreparedMap, c: Candidate, params: MergeParams,
             step: bool = False) -> Candidate:
    """The hypothesis pulled onto a's occupied cells by ICP (unchanged when refinement is off); step:
    then moved by whole cells while that raises its support (_cell_steps)."""
    if not (params.refine and len(a.summary.occupied_m) and len(b.summary.occupied_m)):
        return c
    src, normals = _refine_points(b, params)
    normals = normals if params.refine_facing else None
    t, frac = icp(a.occupied, src, c.transform, params.refine_iterations, normals)
    if step:
        t = _cell_steps(a, b, t, params)
    inliers = int(round(frac * len(src))) if c.source in ("search", "given") else c.inliers
    return Candidate(t, inliers, c.source)


def _cell_steps(a: PreparedMap, b: PreparedMap, t: np.ndarray, params: MergeParams) -> np.ndarray:
    """t moved by whole cells of a in x and y, one step to the best of the eight neighbours at a time,
    while that raises the support (params.refine_cell_steps steps at most); t itself when no step
    does."""
    step = a.grid.resolution
    support = agreement(a.summary, b.summary, t).support(params.conflict_weight)
    for _ in range(params.refine_cell_steps):
        moves = []
        for dx in (-1, 0, 1):
            for dy in (-1, 0, 1):
                if dx or dy:
                    m = t.copy()
                    m[0, 3] += dx * step
                    m[1, 3] += dy * step
                    moves.append((agreement(a.summary, b.summary, m).support(params.conflict_weight), m))
        best, m = max(moves, key=lambda x: x[0])
        if best <= support:
            break
        support, t = best, m
    return t


def _subcell(a: PreparedMap, b: PreparedMap, c: Candidate, params: MergeParams) -> Candidate:
    """The chosen hypothesis fitted to a fraction of a cell (refine.field_fit: b's occupied cells on
    the distance to a's same-facing surfaces, 6 DoF); done once, for the winner (fitting every
    candidate before ranking them costs a third more CPU and, on the fresh worlds of scripts/bench
    merge, let a 180-degree turn of a corridor outrank the truth)."""
    if not (params.refine and params.refine_subcell and len(b.summary.occupied_m)):
        return c
    occupied = b.summary.occupied_m
    points = occupied[:: max(1, -(-len(occupied) // max(1, params.refine_field_max_points)))]
    normals = free_sides(b.grid.cells, params.occupied_threshold, b.grid.offset, b.grid.resolution, points)
    fit = field_fit(a.grid.cells, a.grid.offset, a.grid.resolution, params.occupied_threshold, points,
                    normals, c.transform)
    return Candidate(fit.transform, c.inliers, c.source)


UNPINNED = "the overlap does not pin b"
"""In the reason of a fit refused because b turned or slid agrees about as well (validation.loosest_move)."""

SHARE_TOO_SMALL = "of the maps' structure agrees"
"""In the reason of a fit refused for its overlap share (min_overlap; the score is checked after it)."""


def refused_for_size(r: MergeResult, params: MergeParams) -> bool:
    """Whether r was refused in a way a global map many times the map's size brings about: for its
    overlap share alone (its score passed; the global map's structure far from the map dilutes it), or
    as ambiguous (maps fused with centimetres of error blur repeated structure such as shelf rows). An
    overlap that does not pin b (UNPINNED) pins it less on a smaller map: not that."""
    return ((r.ambiguous and UNPINNED not in r.reason)
            or (not r.accepted and SHARE_TOO_SMALL in r.reason and r.score >= params.min_score))


def share(ag: Agreement, a: PreparedMap, b: PreparedMap) -> float:
    """Agreeing share of both maps' vertical-structure samples."""
    return ag.agree / max(1, len(a.summary.sample_m) + len(b.summary.sample_m))


def rejection(ag: Agreement, inliers: int, overlap: float, params: MergeParams) -> str | None:
    """Why a validated hypothesis cannot be accepted on its own merits, or None."""
    if inliers < params.min_inliers:
        return f"{inliers} inliers < {params.min_inliers}"
    if ag.agree < params.min_agreement:
        return f"overlap too small: {ag.agree} agreeing cells < {params.min_agreement}"
    if overlap < params.min_overlap:
        return f"overlap too small: {overlap:.3f} {SHARE_TOO_SMALL} < {params.min_overlap}"
    if ag.score < params.min_score:
        return f"score {ag.score:.3f} < {params.min_score}"
    return None


def judge(a: PreparedMap, b: PreparedMap, transform: np.ndarray, params: MergeParams) -> MergeResult:
    """One given hypothesis refined and validated alone (no runner-up test): what validation makes of
    any transform, e.g. a deliberately wrong one."""
    c = _subcell(a, b, _refined(a, b, Candidate(np.asarray(transform, dtype=np.float64), 0, "given"), params),
                 params)
    ag = agreement(a.summary, b.summary, c.transform)
    overlap = share(ag, a, b)
    reason = rejection(ag, c.inliers, overlap, params) or "accepted"
    return MergeResult(reason == "accepted", c.transform, c.inliers, ag.score, ag.agree, ag.conflicts, 0.0,
                       reason, overlap)


def as_given(a: PreparedMap, b: PreparedMap, transform: np.ndarray, params: MergeParams,
             method: str = "given") -> MergeResult:
    """A transform validated as it is, without refinement (min_inliers aside: no ICP ran)."""
    ag = agreement(a.summary, b.summary, transform)
    overlap = share(ag, a, b)
    reason = rejection(ag, params.min_inliers, overlap, params) or "accepted"
    return MergeResult(reason == "accepted", transform, 0, ag.score, ag.agree, ag.conflicts, 0.0, reason,
                       overlap, method=method)


def distinct(t1: np.ndarray, t2: np.ndarray, angle_deg: float = 5.0, shift_m: float = 1.0) -> bool:
    """Two transforms that are different hypotheses (> 5 deg or > 1 m apart), not one refined twice."""
    return (rotation_angle_deg(t1[:3, :3].T @ t2[:3, :3]) > angle_deg
            or float(np.linalg.norm(t1[:3, 3] - t2[:3, 3])) > shift_m)


def close_runner_up(runner_support: float, winner_support: float, min_margin: float) -> bool:
    """Whether a distinct runner-up explains the maps about as well as the winner (within min_margin of
    its support). merge_prepared takes the lower of the winner's support before and after its sub-cell
    fit: on a wrong hypothesis the fit can lose most of it (a 180-degree turn of a corridor, support
    6 983 before, 110 after, against the truth's 5 109), and the runner-up must be measured against
    what is accepted."""
    return runner_support >= (1.0 - min_margin) * winner_support


def merge_prepared(a: PreparedMap, b: PreparedMap, params: MergeParams,
                   tm: dict | None = None, known: list[np.ndarray] = ()) -> MergeResult:
    """merge_pair on prepared maps. known: transforms found before (e.g. the last accepted one) that
    compete with the search's hypotheses on equal terms."""
    tm = {} if tm is None else tm
    complete(a, params, tm)
    complete(b, params, tm)
    cands: list[Candidate] = []
    if params.search:
        t0 = time.perf_counter()
        la = a.level if a.level is not None else np.eye(4)
        lb = b.level if b.level is not None else np.eye(4)
        found = yaw_search.search(a.levelled, b.levelled, params, params.search_candidates)
        cands += [Candidate(invert(la) @ t @ lb, 0, "search") for _, t in found]
        tm["search"] = time.perf_counter() - t0
    if params.hypotheses > 0:
        cands += _feature_candidates(a, b, params, tm)
    t0 = time.perf_counter()
    strongest = cands[0] if cands and cands[0].source == "search" else None  # the search's top peak
    if params.refine and len(cands) > params.refine_candidates:
        coarse = [agreement(a.summary, b.summary, c.transform).support(params.conflict_weight) for c in cands]
        cands = [cands[i] for i in np.argsort(coarse)[::-1][: params.refine_candidates]]
    cands += [Candidate(np.asarray(t, dtype=np.float64), 0, "given") for t in known]  # always refined
    scored: list[tuple[float, Agreement, Candidate]] = []
    stepped = None  # the strongest peak as refined and stepped
    for c in cands:
        refined = _refined(a, b, c, params, step=c is strongest)
        stepped = refined if c is strongest else stepped
        ag = agreement(a.summary, b.summary, refined.transform)
        scored.append((ag.support(params.conflict_weight), ag, refined))
    tm["validate"] = time.perf_counter() - t0
    if not scored:
        return MergeResult(False, np.eye(4), 0, 0.0, 0, 0, 0.0, "no hypothesis (no correspondences)",
                           timings=tm)
    scored.sort(key=lambda x: -x[0])
    _, best_ag, best = scored[0]
    t0 = time.perf_counter()
    best = _subcell(a, b, best, params)
    best_ag = agreement(a.summary, b.summary, best.transform)
    tm["subcell"] = time.perf_counter() - t0
    runner = next((s for s in scored[1:] if distinct(s[2].transform, best.transform)), None)
    if runner is not None and stepped is not None and scored[0][2] is stepped:
        moved = _cell_steps(a, b, runner[2].transform, params)  # stepped as the winner was: a fair margin
        if moved is not runner[2].transform:
            ag = agreement(a.summary, b.summary, moved)
            runner = (ag.support(params.conflict_weight), ag,
                      Candidate(moved, runner[2].inliers, runner[2].source))
    runner_score = runner[1].score if runner else 0.0
    overlap = share(best_ag, a, b)
    reason = rejection(best_ag, best.inliers, overlap, params) or "accepted"
    top = min(scored[0][0], best_ag.support(params.conflict_weight))
    if reason == "accepted" and runner is not None and close_runner_up(runner[0], top, params.min_margin):
        reason = f"{AMBIGUOUS}: a distinct hypothesis scores {runner[1].score:.3f} with support " \
                 f"{runner[0]:.0f} vs {top:.0f}"
    if reason == "accepted":
        move, kept = loosest_move(a.summary, b.summary, best.transform, params.conflict_weight,
                                  params.pin_turn_deg, params.pin_slide_m)
        if kept >= 1.0 - params.min_margin:
            reason = f"{AMBIGUOUS}: {move} keeps {kept:.0%} of the support; {UNPINNED}"
    return MergeResult(reason == "accepted", best.transform, best.inliers, best_ag.score, best_ag.agree,
                       best_ag.conflicts, runner_score, reason, overlap, tm)


def comparable(grid: OccupancyGrid, resolution: float) -> OccupancyGrid:
    """The grid as merging compares it with a map of `resolution`: coarsened to it when finer; kept as
    it is when coarser, since every stage works in metres and refining only makes surfaces blocky
    (scripts/bench merge: B at 0.05 or 0.2 m against A at 0.1 m merges best this way)."""
    return resample(grid, resolution) if grid.resolution < resolution * (1 - 1e-9) else grid


def merge_pair(a: OccupancyGrid, b: OccupancyGrid, params: MergeParams | None = None) -> MergeResult:
    """Find, validate and report the transform carrying b's frame into a's (no initial guess); a b of
    another resolution as comparable() makes it."""
    params = params or coopd_params()
    b = comparable(b, a.resolution)
    tm: dict = {}
    pa = prepare(a, params, tm)
    pb = prepare(b, params, tm)
    return merge_prepared(pa, pb, params, tm)

"""Every merging parameter in one frozen dataclass; `thesis_params()` reproduces chapter 8's defaults."""

import math
from dataclasses import dataclass, replace


@dataclass(frozen=True)
class MergeParams:
    """Parameters of the whole pipeline. Distances in metres unless the name says cells."""

    # --- salt-noise filter (coopd; before every stage, see preprocess.despeckle)
    despeckle_max_occupied: int = 3
    """An occupied cell with at most this many occupied neighbours (of 26) and more free than unknown
    ones is dropped to unknown (preprocess.despeckle); -1 switches the filter off."""
    despeckle_passes: int = 3
    """Passes of the filter on a noisy map: a speckle that lost its neighbours in one goes in the next."""
    despeckle_min_share: float = 0.05
    """...only when such cells are at least this share of the occupied cells (salt noise, not a few
    thin structures of a clean map)."""
    # --- preprocessing (§8.1)
    dilate_radius: int = 1
    dilate_iterations: int = 1
    erode_radius: int = 1
    erode_iterations: int = 1
    gaussian_radius: int = 3
    gaussian_sigma: float = 1.0
    gaussian_iterations: int = 1
    downsample_radius: int = 1
    """DS_r: blocks of 2*DS_r cells per axis are averaged (eq. 34's factor)."""
    occupied_threshold: int = 50
    # --- FAST 3D (§8.2)
    fast_radius: int = 3
    fast_continuity: int = 9
    fast_threshold: float = 80.0
    """On intensities 0..255 (occupancy * 2.55), as for images."""
    fast_both_polarities: bool = True
    """Also accept cells darker than their ring (convex corners); the thesis tests brighter only."""
    # --- keypoint filter (§8.3)
    filter_score_radius: int = 1
    filter_adjacent_radius: float = 1.0
    max_keypoints: int = 1500
    """Strongest keypoints kept per map after suppression (bounds matching and memory)."""
    # --- orientation (§8.4)
    orientation_mode: str = "global"
    """'global' (potential field over the whole map) or 'local' (a cube of orientation_radius)."""
    orientation_radius: int = 4
    gauss_seidel_iterations: int = 20
    """Relaxation sweeps of the potential field (whichever the solver)."""
    orientation_solver: str = "jacobi"
    """'jacobi' (order-independent, follows a turn of the map) or 'gauss_seidel' (the thesis, in place)."""
    orientation_window: int = 4
    """Radius (cells) of the Gaussian-weighted ball the field's gradient is averaged over; 0 reads one
    central difference as eq. 20 does."""
    # --- steered BRIEF 3D (§8.5)
    descriptor_tests: int = 256
    descriptor_window: int = 31
    descriptor_seed: int = 42
    descriptor_neighbourhood: int = 0
    descriptor_steering: str = "yaw"
    """How the keypoint orientation turns the test sample: 'yaw' (about the vertical only) or 'euler'
    (the full rotation from alpha, beta, gamma of eq. 20, as Algorithm 4 reads). alpha and beta mix
    horizontal gradient components, so they do not follow a yaw turn of the map: with 'euler' the true
    correspondences of a copy turned by 90 or 180 degrees land at random Hamming distances."""
    # --- matching (§8.6)
    match_max_distance: int = 20
    """CC_d: the thesis accepts pairs with Hamming distance <= 20."""
    match_best_k: int = 0
    """0: every pair within CC_d (thesis). k > 0: each keypoint of b keeps its k nearest in a."""
    match_chunk: int = 512
    # --- correspondence filter (§8.7)
    ransac_model: str = "homography"
    """'homography' (thesis, 5 points), 'rigid' (3-point Kabsch) or 'yaw' (2-point, gravity-aligned)."""
    ransac_iterations: int = 1000
    ransac_tolerance_cells: float = 3.0
    """t, in downsampled cells."""
    ransac_seed: int = 1
    ransac_min_consensus: int = 3
    """Correspondences beyond the minimal sample (5, 3 or 2) that must agree with a hypothesis under
    its rigid fit: the gate that lets RANSAC refuse random correspondences."""
    hypotheses: int = 1
    """Distinct feature-based candidate transforms handed on to validation (the thesis keeps only the
    best); 0 switches the feature stages off."""
    # --- gravity-aligned global search (coopd)
    search: bool = False
    """Propose hypotheses by the exhaustive yaw + shift search of yaw_search (needs gravity)."""
    level: bool = True
    """Level each map (level.py) before the search, so a few degrees of roll/pitch do not hide walls."""
    level_max_tilt_deg: float = 5.0
    search_cell_m: float = 0.3
    search_yaw_step_deg: float = 2.0
    search_wall_cells: int = 3
    search_free_penalty: float = 2.0
    search_free_cells: int = 5
    """A column counts as seen free with no occupied and at least this many free cells in the slab."""
    search_wall_weight_cap: int = 1
    """Wall columns weigh min(occupied cells, cap): 1 makes the wall image binary."""
    search_slab_margin_m: float = 0.4
    """The slab searched leaves out this much above the floor and below the ceiling (at most a quarter
    of the range each: outdoors the 'ceiling' is the top of 0.9 m barriers)."""
    search_peaks_per_yaw: int = 2
    search_suppress_m: float = 1.5
    search_distinct_deg: float = 6.0
    search_distinct_m: float = 1.5
    """Across yaws, a peak within search_distinct_deg and search_distinct_m (where b's centre lands)
    of a stronger one is a near-copy of it and is not handed on (yaw_search.distinct_peaks); 0
    degrees keeps every peak."""
    search_candidates: int = 6
    """Best search peaks refined and validated."""
    # --- MTM and refinement (§8.8)
    gravity_aligned: bool = False
    """Estimate yaw + translation only (drones share gravity through their IMUs)."""
    refine: bool = False
    refine_iterations: int = 28
    """ICP steps: the first half shrink the correspondence radius from 6 to 1.5 cells, the rest hold it
    (14 left some transforms 0.2 m short of convergence)."""
    refine_max_points: int = 4000
    refine_cell_steps: int = 3
    """After ICP, the search's strongest peak is moved by one cell at a time along x or y (or both)
    while that raises its support, at most this many steps: ICP between cell centres can stop two
    cells off the truth in dense structure (a warehouse's shelves in the whole-building maps of
    scripts/bench thesis), where the conflicts of that slide ranked the right hypothesis last.
    Only that peak: stepping every hypothesis lets wrong ones gain as much (in scripts/bench merge
    it merged a pair of maps 16 m apart)."""
    refine_facing: bool = True
    """ICP pairs a cell of b only with cells of a seen from the same side (refine.facing_bits): where
    each map saw a wall from its own side, plain ICP pulled the two sides together (0.14 m and three
    times the conflicts from the exact truth on fresh-world pairs), and the right hypothesis then
    ranked below a wrong one."""
    refine_subcell: bool = True
    """After ICP, fit the chosen transform to a fraction of a cell (refine.field_fit: 6-DoF
    Levenberg-Marquardt of b's occupied cells on the trilinear distance to a's occupied cells that
    face the same way): ICP between cell centres stops up to a cell off, and pulls the two sides of
    a wall seen from opposite sides together."""
    refine_field_max_points: int = 20000
    """b's occupied cells the sub-cell fit moves, thinned evenly to about this many."""
    refine_candidates: int = 6
    """Candidates refined and validated; beyond this many (the feature variants add hypotheses) the
    best by unrefined support go on. Every search hypothesis is refined (6 = search_candidates):
    before ICP one is up to a search cell and a yaw step off, and its conflicts are misalignment as
    much as evidence, so a cut on them dropped the true fit of the racetrack (thin 0.9 m barriers)
    for a clean but wrong one once a conflict weighed 20 agreements."""
    # --- validation (coopd; the thesis leaves it as future work)
    min_inliers: int = 5
    validation_max_points: int = 30000
    validation_min_height_m: float = 0.3
    """Validation samples occupied cells on vertical structure: runs of occupied cells straight above
    one another at least this tall, and at least two cells (validation_min_run): 3 cells at 0.1 m, 2
    at 0.2 m. A floor is often two cells thick and a tilted one steps up a cell every few metres, so
    a run of two 0.1 m cells is no wall; outdoors, where few walls are seen, such floor cells were
    most of the samples and wrong fits that lay ground on ground validated (scripts/bench merge)."""
    min_score: float = 0.94
    """Agreement of overlapping known cells: agree / (agree + occupied-vs-free conflicts). Real flight
    maps carry drift: correct transforms score 0.94-1.0 there (0.977-0.988 in the daemons' demo
    maps); wrong ones up to 0.86 on the synthetic set and 0.91 (a 0.8 m slide along the racetrack)
    on real maps, but 0.95-0.99 in symmetric buildings: the score alone cannot tell, the ranking
    by support among distinct fits does (conflict_weight, min_margin)."""
    conflict_weight: float = 20.0
    """Support = agreements - conflict_weight * conflicts: ranks hypotheses and sets the margin.
    A conflict (a wall where the other map saw through) is strong evidence, an agreement weak: in
    symmetric buildings the mirror or corridor-shifted fit of the drones' maps overlaps more than the
    true one (their routes are symmetric too) but conflicts at 1-4 % of its agreements against
    0.2-2 % for the truth (tests/merging/test_recheck.py holds such a pair). With the daemon's
    rechecks, `scripts/bench merge_replay` over 11 recorded flights ends 42 of 42 pairs outside the
    hospital right (weight 3 without rechecks: 36, 5 of them flipped; docs/accuracy.md)."""
    min_agreement: int = 600
    """Occupied cells of either map that land on the other's occupied surface."""
    min_overlap: float = 0.2
    """Agreeing share of both maps' vertical-structure samples: a transform that only touches the
    other map at its border agrees everywhere it overlaps, but overlaps little."""
    min_margin: float = 0.15
    """A distinct runner-up (> 5 deg or > 1 m away) must stay below (1 - min_margin) of the best
    support: two fits that explain the maps about as well leave the choice to later, larger maps."""
    pin_turn_deg: float = 10.0
    pin_slide_m: float = 1.0
    """The winner must lose more than min_margin of its support when b is turned by pin_turn_deg about
    where the maps agree or slid by pin_slide_m along or across that agreement
    (validation.loosest_move): an overlap of one pole or one straight wall agrees as well turned or
    slid, and is reported as ambiguous."""
    # --- multi-map (§8, Figure 35)
    max_rounds: int = 3

    def with_(self, **changes) -> "MergeParams":
        return replace(self, **changes)

    def validation_min_run(self, resolution: float) -> int:
        """validation_min_height_m in whole cells of a map of this resolution (rounded up), at least 2."""
        return max(2, math.ceil(self.validation_min_height_m / resolution - 1e-9))


def thesis_params() -> MergeParams:
    """Chapter 8's stages (FAST 3D, steered BRIEF 3D, matches within CC_d = 20, RANSAC, Kabsch) with
    the settings that make them merge, each measured by `scripts/bench thesis` (docs/merging.md,
    "The thesis pipeline"): yaw-steered descriptors, keypoints of both polarities, each keypoint's 3
    nearest matches, the 2-point yaw estimator with its consensus gate, 3 hypotheses for the runner-up
    test, ICP and validation."""
    return MergeParams(fast_both_polarities=True, match_best_k=3, ransac_model="yaw", ransac_iterations=3000,
                       hypotheses=3, refine=True)


def coopd_params() -> MergeParams:
    """coopd's default: gravity-aligned global search, ICP refinement, validation; no feature stage
    (on ray-cast partial maps the feature correspondences were almost all wrong, see docs/merging.md)."""
    return MergeParams(gravity_aligned=True, refine=True, search=True, hypotheses=0)


def features_params() -> MergeParams:
    """The thesis features feeding coopd's back end: gravity-steered BRIEF, 2-point yaw RANSAC with
    several hypotheses, refinement and validation."""
    return MergeParams(fast_both_polarities=True, match_best_k=3, match_max_distance=80,
                       ransac_model="yaw", ransac_iterations=3000, hypotheses=8,
                       gravity_aligned=True, refine=True)


def rigid_params() -> MergeParams:
    """6-DoF variant: 3-point Kabsch RANSAC with validation and refinement (no gravity assumption)."""
    return features_params().with_(ransac_model="rigid", gravity_aligned=False, ransac_iterations=5000)


VARIANTS = {"coopd": coopd_params, "features": features_params, "rigid": rigid_params,
            "thesis": thesis_params}

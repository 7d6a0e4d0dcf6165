"""Multi-map merging (§8, Figure 35): the own map is the reference; received maps merge one by one
into the growing global map, and maps that failed are retried once the global map has grown (region
inheritance). Every merged map's transform into the global (= reference) frame is reported."""

import time
from dataclasses import dataclass

import numpy as np

from ..grid import OccupancyGrid, fuse_transformed
from .pair import MergeResult, merge_prepared, prepare
from .params import MergeParams, coopd_params


@dataclass(frozen=True)
class GlobalMergeResult:
    """The global map and, per input map (in the order given), how it merged."""

    global_map: OccupancyGrid
    results: list[MergeResult]
    rounds: int

    @property
    def transforms(self) -> list[np.ndarray | None]:
        """Each map's transform into the global frame (None when it was not merged)."""
        return [r.transform if r.accepted else None for r in self.results]


def merge_all(reference: OccupancyGrid, others: list[OccupancyGrid],
              params: MergeParams | None = None) -> GlobalMergeResult:
    """Merge others into a copy of reference, retrying failures while the global map keeps growing."""
    params = params or coopd_params()
    world = reference.copy()
    prepared_world = None
    results: list[MergeResult | None] = [None] * len(others)
    prepared_others = [None] * len(others)
    rounds = 0
    pending = list(range(len(others)))
    while pending and rounds < params.max_rounds:
        rounds += 1
        merged_now = []
        for i in pending:
            tm: dict = {}
            t0 = time.perf_counter()
            if prepared_world is None:
                prepared_world = prepare(world, params, tm)
            if prepared_others[i] is None:
                prepared_others[i] = prepare(others[i], params, tm)
            r = merge_prepared(prepared_world, prepared_others[i], params, tm)
            if r.accepted:
                t1 = time.perf_counter()
                fuse_transformed(world, others[i], r.transform, params.occupied_threshold)
                tm["fuse"] = time.perf_counter() - t1
                prepared_world = None
                merged_now.append(i)
            tm["total"] = time.perf_counter() - t0
            results[i] = MergeResult(r.accepted, r.transform, r.inliers, r.score, r.agreement, r.conflicts,
                                     r.runner_up_score, r.reason, r.overlap, tm)
        pending = [i for i in pending if i not in merged_now]
        if not merged_now:
            break
    return GlobalMergeResult(world, results, rounds)

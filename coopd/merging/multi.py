"""Multi-map merging (§8, Figure 35): the own map is the reference; received maps merge one by one
into the growing global map, and maps that failed are retried once the global map has grown (region
inheritance). Every merged map's transform into the global (= reference) frame is reported."""

import time
from dataclasses import dataclass, field, replace

import numpy as np

from ..grid import OccupancyGrid, fuse_transformed
from .hints import Hint, resolve, try_hints
from .pair import MergeResult, merge_prepared, prepare
from .params import MergeParams, coopd_params


@dataclass(frozen=True)
class GlobalMergeResult:
    """The global map and, per input map (in the order given), how it merged."""

    global_map: OccupancyGrid
    results: list[MergeResult]
    rounds: int
    hints_refused: list[int] = field(default_factory=list)
    """Per input map: hints tried that failed validation (the full search then ran)."""

    @property
    def transforms(self) -> list[np.ndarray | None]:
        """Each map's transform into the global frame (None when it was not merged)."""
        return [r.transform if r.accepted else None for r in self.results]


def _order(pending: list[int], hints: list[list[Hint]]) -> list[int]:
    """Maps whose hints lean on another pending map (via) go after it, so the hint can resolve."""
    first = [i for i in pending if not any(h.via in pending for h in hints[i])]
    return first + [i for i in pending if i not in first]


def merge_all(reference: OccupancyGrid, others: list[OccupancyGrid],
              params: MergeParams | None = None, hints: list[list[Hint]] | None = None) -> GlobalMergeResult:
    """Merge others into a copy of reference, retrying failures while the global map keeps growing.
    hints[i]: candidate transforms for others[i] (hints.py), tried before the full search."""
    params = params or coopd_params()
    hints = [list(h) for h in hints] if hints is not None else [[] for _ in others]
    if len(hints) != len(others):
        raise ValueError(f"{len(hints)} hint lists for {len(others)} maps")
    world = reference.copy()
    prepared_world = None
    results: list[MergeResult | None] = [None] * len(others)
    prepared_others = [None] * len(others)
    refused = [0] * len(others)
    merged: dict[int, np.ndarray] = {}
    rounds = 0
    pending = list(range(len(others)))
    while pending and rounds < params.max_rounds:
        rounds += 1
        merged_now = []
        for i in _order(pending, hints):
            tm: dict = {}
            t0 = time.perf_counter()
            if prepared_world is None:
                prepared_world = prepare(world, params, tm, lazy=True)
            if prepared_others[i] is None:
                prepared_others[i] = prepare(others[i], params, tm, lazy=True)
            candidates = [(t, h.source) for h in hints[i] if (t := resolve(h, merged)) is not None]
            r, n = try_hints(prepared_world, prepared_others[i], candidates, params)
            refused[i] += n
            if r is None:
                r = merge_prepared(prepared_world, prepared_others[i], params, tm)
            if r.accepted:
                t1 = time.perf_counter()
                fuse_transformed(world, others[i], r.transform, params.occupied_threshold)
                tm["fuse"] = time.perf_counter() - t1
                prepared_world = None
                merged_now.append(i)
                merged[i] = r.transform
            tm["total"] = time.perf_counter() - t0
            results[i] = replace(r, timings=tm)
        pending = [i for i in pending if i not in merged_now]
        if not merged_now:
            break
    return GlobalMergeResult(world, results, rounds, refused)

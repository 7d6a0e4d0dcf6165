"""Multi-map merging (§8, Figure 35): the own map is the reference; received maps merge one by one
into the growing global map, and maps that failed are retried once the global map has grown (region
inheritance). Every merged map's transform into the global (= reference) frame is reported."""

import time
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field, replace

import numpy as np

from ..grid import OccupancyGrid, fuse_transformed, resample
from .hints import Hint, check_vouched, resolve, try_hints
from .pair import (
    MergeResult,
    comparable,
    complete,
    distinct,
    merge_prepared,
    prepare,
    refused_for_size,
)
from .params import MergeParams, coopd_params


@dataclass(frozen=True)
class GlobalMergeResult:
    """The global map and, per input map (in the order given), how it merged."""

    global_map: OccupancyGrid
    results: list[MergeResult]
    rounds: int
    hints_refused: list[int] = field(default_factory=list)
    """Per input map: hint validations that failed (work spent on hints that did not serve)."""
    full_registrations: int = 0
    """Full searches run (a map retried in a later round counts again): the work hints save."""
    vouched: int = 0
    """Maps merged by a vouched hint (hints.check_vouched): checked, not refined."""
    worker_cpu_s: float = 0.0
    """CPU time of the searches run on worker threads (workers > 1), which the caller's thread time
    does not include."""

    @property
    def transforms(self) -> list[np.ndarray | None]:
        """Each map's transform into the global frame (None when it was not merged)."""
        return [r.transform if r.accepted else None for r in self.results]


def waiting_result() -> MergeResult:
    """The result of a map left out because its full search waits for a peer's merge result
    (merge_all's hints_only, no hint validated)."""
    return MergeResult(False, np.eye(4), 0, 0.0, 0, 0, 0.0,
                       "deferred: full search left to a peer's merge result", method="deferred")


def _order(pending: list[int], hints: list[list[Hint]]) -> list[int]:
    """Maps whose hints lean on another pending map (via) go after it, so the hint can resolve."""
    first = [i for i in pending if not any(h.via in pending for h in hints[i])]
    return first + [i for i in pending if i not in first]


class _World:
    """The growing global map, prepared again only after something was fused into it."""

    def __init__(self, reference: OccupancyGrid, params: MergeParams):
        self.grid = reference.copy()
        self.params = params
        self._prepared = None
        self.generation = 0
        """Maps fused so far: a search's result holds only for the global map it ran on."""

    def prepared(self, tm: dict):
        if self._prepared is None:
            self._prepared = prepare(self.grid, self.params, tm, lazy=True)
        return self._prepared

    def fuse(self, grid: OccupancyGrid, transform: np.ndarray, tm: dict) -> None:
        t0 = time.perf_counter()
        same = resample(grid, self.grid.resolution)
        fuse_transformed(self.grid, same, transform, self.params.occupied_threshold)
        tm["fuse"] = time.perf_counter() - t0
        self._prepared = None
        self.generation += 1


class _SearchesAhead:
    """Full searches started on worker threads before their turn, for maps whose accepted result
    will be held out of the global map: while nothing is fused, the global map they run against is
    the one their turn would give them, so merge_all's results are those of one search at a time.
    A result is taken only if the global map is still the one it ran on (else searched again)."""

    def __init__(self, workers: int, ahead: Callable[[int], bool] | None):
        self.ahead = ahead
        self.slots = max(0, workers - 1) if ahead is not None else 0
        self.pool = ThreadPoolExecutor(self.slots, thread_name_prefix="merge-search") if self.slots else None
        self.running: dict[int, tuple[int, Future]] = {}
        """Map -> (world generation it runs on, its search)."""
        self.started: list[Future] = []
        self.cpu_s = 0.0
        """CPU time of every search started here, summed once they are done (close)."""

    def start(self, todo: list[int], world: "_World", prepared: Callable, params: MergeParams,
              skip: frozenset[int]) -> None:
        """Start the searches of the maps after todo[0] that may run ahead, up to the free slots.
        Both maps are completed here first: the worker threads only read them."""
        if self.pool is None:
            return
        for j in [j for j in self.running if j not in todo]:  # merged meanwhile (a hint): not needed
            del self.running[j]
        for j in todo[1:]:
            if len(self.running) >= self.slots:
                return
            if j in self.running or j in skip or not self.ahead(j):
                continue
            tm: dict = {}
            a, b = world.prepared(tm), prepared(j, tm)
            complete(a, params, tm)
            complete(b, params, tm)
            self.running[j] = (world.generation, self.pool.submit(_timed_search, a, b, params, tm))
            self.started.append(self.running[j][1])

    def take(self, i: int, generation: int) -> tuple[MergeResult, dict] | None:
        """Map i's search run ahead on the global map of `generation`, or None."""
        entry = self.running.pop(i, None)
        if entry is None:
            return None
        r, tm, _ = entry[1].result()
        return (r, tm) if entry[0] == generation else None

    def close(self) -> None:
        """Wait for every search still running (their results are not needed) and stop the threads."""
        if self.pool is not None:
            self.pool.shutdown(wait=True, cancel_futures=True)
            self.running.clear()
            self.cpu_s = sum(f.result()[2] for f in self.started if not f.cancelled())


def _timed_search(a, b, params: MergeParams, tm: dict) -> tuple[MergeResult, dict, float]:
    """merge_prepared on a worker thread: (result, timings with its total, CPU seconds it took)."""
    t0, cpu0 = time.perf_counter(), time.thread_time()
    r = merge_prepared(a, b, params, tm)
    tm["total"] = time.perf_counter() - t0
    return r, tm, time.thread_time() - cpu0


def merge_all(reference: OccupancyGrid, others: list[OccupancyGrid],
              params: MergeParams | None = None, hints: list[list[Hint]] | None = None,
              hints_only: frozenset[int] = frozenset(),
              contest: frozenset[int] = frozenset(),
              hold: Callable[[int, MergeResult], bool] | None = None,
              ahead: Callable[[int], bool] | None = None, workers: int = 1) -> GlobalMergeResult:
    """Merge others into a copy of reference, retrying failures while the global map keeps growing.

    hints[i]: candidate transforms for others[i] (hints.py). Hints go first and are retried whenever
    the global map grew (a hint of a map that overlaps only a later one fails against the reference
    alone); a map's full search runs only when none of its hints validates now, and never for the
    maps in hints_only (their full search is left to a peer whose result will come as a hint).
    The maps in contest are not merged by a hint alone: their full search runs and their hints
    compete with its hypotheses under the runner-up margin (a transform accepted on small early maps
    of a symmetric building is checked against the alternatives once the maps grew).
    hold(i, result): an accepted map it returns True for is reported (and its transform resolves
    other maps' hints) but not fused into the global map: a provisional merge, not yet trusted.
    ahead(i): True when map i's accepted result is sure to be held; with workers > 1, the full
    searches of such maps run `workers` at a time (_SearchesAhead), with the results of one at a time.
    A map of another resolution than the reference's is compared as pair.comparable makes it and
    resampled to the reference's resolution when fused (transforms are in metres)."""
    params = params or coopd_params()
    hints = [list(h) for h in hints] if hints is not None else [[] for _ in others]
    if len(hints) != len(others):
        raise ValueError(f"{len(hints)} hint lists for {len(others)} maps")
    world = _World(reference, params)
    results: list[MergeResult | None] = [None] * len(others)
    prepared_others = [None] * len(others)
    refused = [0] * len(others)
    full = 0
    checked = [0]
    merged: dict[int, np.ndarray] = {}

    def prepared(i: int, tm: dict):
        if prepared_others[i] is None:
            prepared_others[i] = prepare(comparable(others[i], reference.resolution), params, tm, lazy=True)
        return prepared_others[i]

    reference_alone: list = [None]

    def reference_prepared(tm: dict):
        """The reference map alone, prepared: the world's preparation while nothing is fused yet."""
        if world.generation == 0:
            return world.prepared(tm)
        if reference_alone[0] is None:
            reference_alone[0] = prepare(reference, params, tm, lazy=True)
        return reference_alone[0]

    def finish(i: int, r: MergeResult, tm: dict, t0: float) -> None:
        if r.accepted:
            if hold is None or not hold(i, r):
                world.fuse(others[i], r.transform, tm)
            merged[i] = r.transform
        tm.setdefault("total", time.perf_counter() - t0)  # a search run ahead timed itself
        results[i] = replace(r, timings=tm)

    dead: set[tuple[int, int]] = set()
    """(map, hint position) refused for disagreeing with the global map: not tried again."""
    tried_at: dict[int, int] = {}
    """Map -> maps merged when its hints were last tried: retried only once the global map grew."""

    def vouched(i: int, live: list[int], tm: dict) -> MergeResult | None:
        """Map i merged by its first vouched hint, when every live hint of it agrees with that one and
        the check passes; None: its hints are refined and validated as usual."""
        first = next((hints[i][k] for k in live if hints[i][k].vouched), None)
        if first is None:
            return None
        t = resolve(first, merged)
        if any(distinct(resolve(hints[i][k], merged), t) for k in live):
            return None
        if first.via is None:  # a direct edge: checked on our own map, as the peer found it
            return check_vouched(reference_prepared(tm), prepared(i, tm), first, np.eye(4), params)
        return check_vouched(prepared(first.via, tm), prepared(i, tm), first, merged[first.via], params)

    def search_alone(i: int, r: MergeResult, tm: dict, known: list) -> MergeResult:
        """Map i, refused by the global map in a way its size brings about (pair.refused_for_size),
        searched on the reference alone, the global map's refused fit competing: what a merge with
        every fit held searches (the daemon's first merge), so a map that arrives after the others were
        fused is placed as it would have been with them. Not the global map cut to the fit's
        surroundings: in a building with a 180-degree symmetry the cut validates the mirrored fit."""
        alone = merge_prepared(reference_prepared(tm), prepared(i, tm), params, tm, [*known, r.transform])
        return alone if alone.accepted else r

    def run_hints(todo: list[int]) -> None:
        """Try the hints of every map in todo, again as long as one of them merged."""
        progress = True
        while progress:
            progress = False
            for i in _order([i for i in todo if i not in merged and i not in contest], hints):
                if tried_at.get(i) == len(merged):
                    continue
                tried_at[i] = len(merged)
                live = [k for k, h in enumerate(hints[i])
                        if (i, k) not in dead and resolve(h, merged) is not None]
                if not live:
                    continue
                tm: dict = {}
                t0 = time.perf_counter()
                r = vouched(i, live, tm)
                if r is not None:
                    checked[0] += 1
                    finish(i, r, tm, t0)
                    progress = True
                    continue
                candidates = [(resolve(hints[i][k], merged), hints[i][k].source) for k in live]
                r, n, final = try_hints(world.prepared(tm), prepared(i, tm), candidates, params)
                refused[i] += n
                dead.update((i, live[j]) for j in final)
                if r is not None:
                    finish(i, r, tm, t0)
                    progress = True

    rounds = 0
    pending = list(range(len(others)))
    searches = _SearchesAhead(workers, ahead)
    try:
        while pending and rounds < params.max_rounds:
            rounds += 1
            before = len(merged)
            searched: set[int] = set()
            while True:
                run_hints(pending)
                todo = [i for i in _order(pending, hints)
                        if i not in merged and i not in searched and (i not in hints_only or i in contest)]
                if not todo:
                    break
                i = todo[0]
                searched.add(i)
                searches.start(todo, world, prepared, params, contest)
                t0 = time.perf_counter()
                done = searches.take(i, world.generation)
                known = [t for t in (resolve(h, merged) for h in hints[i]) if t is not None] \
                    if i in contest else []
                if done is not None:
                    r, tm = done
                else:
                    tm = {}
                    r = merge_prepared(world.prepared(tm), prepared(i, tm), params, tm, known)
                full += 1
                if refused_for_size(r, params) and world.generation > 0:
                    r = search_alone(i, r, tm, known)
                    full += 1
                finish(i, r, tm, t0)
            pending = [i for i in pending if i not in merged]
            if len(merged) == before:
                break
    finally:
        searches.close()
    for i in range(len(others)):
        if results[i] is None:  # in hints_only, and no hint validated
            results[i] = waiting_result()
    return GlobalMergeResult(world.grid, results, rounds, refused, full, checked[0], searches.cpu_s)

"""The merging thread: local + received maps -> the global map and the other vehicles' offsets.

Runs at low priority (nice +10), one merge at a time, triggered by a received map (on_receive, once
the burst of arrivals settled), by the period and by `coopctl merge-now`. A merge whose inputs (local
and received map versions) are those of the last merge done is skipped: merging is deterministic, it
would rebuild the same global map (at 10 drones one merge costs the whole period and more).
Received maps rest compressed in the sharing store and are decompressed only inside a merge, under
a "merge-scratch" reservation of the memory budget; a merge that would not fit is deferred and
reported, never half-done.

The registration and fusion are coopd.merging.merge_all(reference, others, params) ->
GlobalMergeResult(global_map, results per input map: accepted, transform, score, reason). In a
build without it the global map is the local map fused with nothing and every merge request
answers "merging: not available in this build".

Map frames are odometry frames: the transform between two of them does not change between merges.
So every accepted transform is kept per vehicle and handed to the next merge as a hint (own warm
start, coopd.merging.hints): ICP + validation instead of the full search. With `distributed`, peers'
published merge results are hints too, and our own accepted transforms are published
(publish_results) for them (thesis §1, §10.4). merge_fn gets hints=... only when there are any.
A hint is judged alone, so once a pair's maps grew (recheck_growth) or stopped growing, the map is
searched again with its hints competing (contest=...): a fit picked on small early maps of a
symmetric building does not live on. A search that finds two fits leaves the map out (contested).
With confirm_before_fusing, a fit newly found by a search is provisional: reported, but held out of
the global map (merge_all(hold=...)) and not published until a recheck on grown maps finds it again
or the maps stop growing. Early wrong fits then never reach the global map. A merge that finds no
map changed since the one that held fits (the maps settled) confirms them without searching again
(the search is deterministic) and fuses them into the global map.
"""

import logging
import math
import threading
import time
from collections.abc import Callable

import numpy as np

from coopd.daemon.budget import BudgetExceeded, MemoryBudget
from coopd.daemon.threads import WorkerProgress
from coopd.geometry import rotation_angle_deg
from coopd.grid import OCCUPIED_THRESHOLD, OccupancyGrid, fuse_transformed
from coopd.sharing.wire import (
    DEFAULT_LIMITS,
    EDGE_FULL,
    MAX_EDGES,
    DecodeLimits,
    MapMeta,
    MergeEdge,
    MergeResultMessage,
    decode_map,
    peek,
)

log = logging.getLogger("coopd.daemon")

NOT_AVAILABLE = "merging: not available in this build"
PROGRESS_NAME = "merging"
"""The merging thread's name in the watchdog's WorkerProgress."""
BEAT_PERIOD_S = 1.0
"""The idle merging thread wakes at least this often to show it is alive."""
SETTLED_GROWTH = 1.01
"""A pair whose known cells grew less than this since the last merge has settled (the flight is over)."""
SETTLED_RECHECK = 1.05
"""A settled pair decided on maps this much smaller is searched once more, on the final maps."""
SCRATCH_BYTES_PER_CELL = 12
"""Merge scratch budgeted per input cell (local + received): the local snapshot and decoded
received maps (1 B each) plus merge_all's own peak, measured with tracemalloc at 5.7-8.5 B per
input cell (global map copy, preprocessing, features) on small_house maps of 0.8-2.6 M cells."""


def mergeable_cells(grid_budget: int, local_cells: int) -> int:
    """The largest received map, in cells, whose merge scratch fits the grid budget next to a local
    snapshot of `local_cells`: a bigger map could never be merged (every merge would be deferred),
    so it is refused at receive and not restored from a checkpoint."""
    return max(0, grid_budget // SCRATCH_BYTES_PER_CELL - local_cells)


def find_merge_all() -> tuple[Callable | None, str | None]:
    """(coopd.merging.merge_all, None) when this build has it, else (None, why). A build without
    the coopd.merging package is a packaging choice (a WARNING); a failure inside it (a dependency
    missing, any error while importing) turns merging off and is an ERROR line with the traceback."""
    try:
        from coopd.merging import merge_all
    except ModuleNotFoundError as e:
        if e.name == "coopd.merging":
            log.warning("%s: the global map is the local map", NOT_AVAILABLE)
            return None, None
        problem = f"importing coopd.merging failed: {type(e).__name__}: {e}"
    except Exception as e:  # ImportError of a dependency, or a bug at import time
        problem = f"importing coopd.merging failed: {type(e).__name__}: {e}"
    else:
        return merge_all, None
    log.error("merging is off: %s", problem, exc_info=True)
    return None, problem


def in_global_map(entry: dict) -> bool:
    """Whether a status merges.offsets entry's map is fused into the global map: accepted, and not
    provisional (held out until confirmed)."""
    return bool(entry.get("accepted")) and not entry.get("provisional")


def offset_summary(transform) -> dict:
    """A transform as an operator reads it: translation in metres and yaw in degrees."""
    t = np.asarray(transform, dtype=np.float64)
    return {
        "translation_m": [round(float(v), 3) for v in t[:3, 3]],
        "yaw_deg": round(math.degrees(math.atan2(t[1, 0], t[0, 0])), 2),
        "transform": [round(float(v), 6) for v in t.reshape(-1)],
    }


class Merger:
    """Owns the global map and the merge counters; run() is the merging thread's loop."""

    def __init__(
        self,
        vehicle_id: int,
        local_snapshot: Callable[[], tuple[OccupancyGrid, int]],
        received_maps: Callable[[], list],
        budget: MemoryBudget,
        period_s: float,
        enabled: bool = True,
        merge_fn: Callable | None = None,
        params=None,
        limits: DecodeLimits = DEFAULT_LIMITS,
        min_gap_s: float = 0.0,
        distributed: bool = True,
        peer_results: Callable[[], list] | None = None,
        publish_results: Callable[[MergeResultMessage], None] | None = None,
        local_version: Callable[[], int] | None = None,
        settle_s: float = 0.0,
        defer_full_s: float = 0.0,
        recheck_growth: float | None = 1.3,
        confirm_before_fusing: bool = False,
        progress: WorkerProgress | None = None,
        start_error: str | None = None,
    ):
        self.vehicle_id = vehicle_id
        self.progress = progress if progress is not None else WorkerProgress([PROGRESS_NAME])
        """The merging thread beats here every loop and merges under working() (watchdog health)."""
        self.start_error = start_error
        """Why merging could not start (e.g. an ImportError inside coopd.merging), for status."""
        self.local_snapshot = local_snapshot
        self.received_maps = received_maps
        self.budget = budget
        self.period_s = period_s
        self.enabled = enabled
        self.merge_fn = merge_fn
        self.params = params
        self.limits = limits
        self.counters = {"done": 0, "failed": 0, "deferred": 0, "nothing_to_merge": 0, "unchanged": 0,
                         "full_registrations": 0, "hinted_own": 0, "hinted_peer": 0, "hint_rejected": 0,
                         "rechecks": 0}
        self.cpu_s = 0.0
        """CPU time of the merging thread inside merges (time.thread_time): the work the bench sums."""
        self.distributed = distributed
        """Use peers' merge results as hints and publish ours; off: own warm start only."""
        self.peer_results = peer_results
        self.publish_results = publish_results
        self._accepted: dict[int, np.ndarray] = {}
        """Vehicle id -> last accepted transform of its map frame into ours (the own hints)."""
        self._result_version = 0
        self._published: dict[int, np.ndarray] = {}
        """Vehicle id -> transform we last published: an unchanged set is not published again (a
        new version would make every peer merge again, and their answers make us merge again)."""
        self.defer_full_s = defer_full_s
        """Distributed: a map's full search waits this long for the swarm's lowest vehicle id to
        publish it (then validating its result is enough); 0: never wait."""
        self.recheck_growth = recheck_growth
        """A merged map is searched again, its known transforms competing, once the known cells of it
        and our map grew this much since it was last decided: a transform accepted on small early maps
        of a symmetric building (a 180-degree flip, a slide along a corridor) is not kept for good.
        None: never re-searched, neither grown nor settled (the rules before rechecks, for benches);
        contested maps still only compete."""
        self._decided_at: dict[int, int] = {}
        """Vehicle id -> known cells of its map and ours when its transform was last decided."""
        self._last_size: dict[int, int] = {}
        """Vehicle id -> known cells of its map and ours at the last merge (to see the maps settle)."""
        self._contested: set[int] = set()
        """Vehicles whose last full search found two fits (ambiguous): their hints only compete."""
        self.confirm_before_fusing = confirm_before_fusing
        """A fit newly found by a search stays out of the global map (provisional) until a recheck on
        maps recheck_growth times larger finds it again or the pair stops growing."""
        self._provisional: set[int] = set()
        """Vehicles whose accepted transform is provisional: reported, held out of the global map."""
        self._held_inputs: tuple | None = None
        """inputs() of the merge that left maps provisional: the same again means they settled."""
        self._edges: dict[int, MergeEdge] = {}
        """Vehicle id -> edge of its accepted transform at the last merge (published once confirmed)."""
        self._first_seen: dict[int, float] = {}
        self._unmerged: set[int] = set()
        self._deferring = False
        """The last merge left a map's full search to a peer: merge again on the period even if
        nothing changed, so that the search runs here once defer_full_s is over."""
        """Vehicles whose maps the last merge left out (refused or deferred)."""
        self.local_version = local_version
        """The local map's version without copying it; given, a merge whose inputs (this and every
        received map's version) equal those of the last merge done is skipped, counted "unchanged"."""
        self._merged_inputs: tuple | None = None
        self.last: dict | None = None
        self.offsets: dict[int, dict] = {}
        self._global: tuple[OccupancyGrid, MapMeta] | None = None
        self._cv = threading.Condition()
        self._requested = 0
        self._urgent = False
        self.min_gap_s = min_gap_s
        """Received maps trigger a merge at most this often (a peer publishes every second)."""
        self.settle_s = settle_s
        """A requested merge waits until no request came for this long (the maps of a sharing burst
        merge together, not the first one alone), but at most max(settle_s, min_gap_s)."""
        self._pending_since: float | None = None
        self._last_request_at = 0.0
        self._completed = 0
        self._reasons: list[str] = []
        self._stop = threading.Event()
        self.busy_since: float | None = None

    @property
    def available(self) -> bool:
        return self.merge_fn is not None

    # ------------------------------------------------------------------------------- requests
    def request(self, reason: str, urgent: bool = False) -> int:
        """Ask for a merge (non-blocking); returns the request number. Urgent: skip min_gap_s."""
        with self._cv:
            self._requested += 1
            self._urgent |= urgent
            self._last_request_at = time.monotonic()
            if self._pending_since is None:
                self._pending_since = self._last_request_at
            if len(self._reasons) < 16:
                self._reasons.append(reason)
            self._cv.notify_all()
            return self._requested

    def merge_now(self, timeout_s: float) -> dict:
        """Request a merge and wait for its outcome (coopctl merge-now)."""
        if not self.enabled:
            return {"outcome": "failed", "detail": "merging is disabled in the configuration"}
        if not self.available:
            return {"outcome": "failed", "detail": self.status()["state"]}
        ticket = self.request("merge-now", urgent=True)
        with self._cv:
            done = self._cv.wait_for(lambda: self._completed >= ticket or self._stop.is_set(), timeout_s)
            if not done or self.last is None:
                return {"outcome": "queued", "detail": f"merge still running after {timeout_s:.0f} s"}
            return {k: self.last[k] for k in ("outcome", "detail", "seconds")}

    def stop(self) -> None:
        self._stop.set()
        with self._cv:
            self._cv.notify_all()

    # ----------------------------------------------------------------------------------- loop
    def run(self) -> None:
        """Merge every period_s, on request (settled, at most one merge per min_gap_s), at once for
        merge-now; skip a merge whose inputs are those of the last one done."""
        next_periodic = time.monotonic() + self.period_s
        not_before = 0.0
        while not self._stop.is_set():
            with self._cv:
                while not self._stop.is_set():
                    self.progress.beat(PROGRESS_NAME)
                    now = time.monotonic()
                    pending = self._requested > self._completed
                    due = max(not_before, self._settled_at()) if pending else next_periodic
                    if self._urgent or now >= due or now >= next_periodic:
                        break
                    self._cv.wait(min(BEAT_PERIOD_S, max(0.0, min(due, next_periodic) - now)))
                if self._stop.is_set():
                    return
                ticket = self._requested
                self._pending_since = None
                urgent, self._urgent = self._urgent, False
                reasons, self._reasons = self._reasons or ["period"], []
            if time.monotonic() >= next_periodic:
                next_periodic = time.monotonic() + self.period_s
            if self.enabled and self.available:
                inputs = self.inputs()
                same = inputs is not None and inputs == self._merged_inputs
                if not urgent and same and not self._deferring and not self._provisional:
                    self.counters["unchanged"] += 1  # merging is deterministic: the same global map again
                else:
                    if self.merge_once(",".join(sorted(set(reasons))))["outcome"] == "done":
                        # with nothing left out, peers' results no longer count (inputs() drops them)
                        done_with_all = inputs is not None and not self._unmerged
                        self._merged_inputs = (*inputs[:2], ()) if done_with_all else inputs
                    not_before = time.monotonic() + self.min_gap_s
                    if self._provisional:  # merge again soon: the maps grew, or they settled
                        self.request("confirm")
            with self._cv:
                self._completed = max(self._completed, ticket)
                self._cv.notify_all()

    def _settled_at(self) -> float:
        """When the pending requests have settled: settle_s after the last one, capped after the first."""
        if self._pending_since is None:
            return 0.0
        cap = self._pending_since + max(self.settle_s, self.min_gap_s)
        return min(self._last_request_at + self.settle_s, cap)

    def inputs(self) -> tuple | None:
        """(local version, (vehicle id, version) of every received map, and of every peer's merge
        results when distributed and a map was left out: a new result may merge it); None
        without local_version."""
        if self.local_version is None:
            return None
        results = ()
        if self.distributed and self.peer_results is not None and self._unmerged:
            results = tuple(sorted((r.vehicle_id, r.version) for r in self.peer_results()))
        return (self.local_version(), tuple(sorted((m.vehicle_id, m.version) for m in self.received_maps())),
                results)

    def merge_once(self, reason: str = "request") -> dict:
        """One merge of the local map with every received map; returns and records the outcome."""
        t0 = time.monotonic()
        cpu0 = time.thread_time()
        self.busy_since = t0
        try:
            with self.progress.working(PROGRESS_NAME):
                outcome, detail = self._merge()
        except Exception as e:  # a merging bug must never take the daemon down
            log.exception("merge failed")
            outcome, detail = "failed", f"{type(e).__name__}: {e}"
        finally:
            self.busy_since = None
            self.cpu_s += time.thread_time() - cpu0
        seconds = time.monotonic() - t0
        key = "nothing_to_merge" if outcome == "nothing" else outcome
        self.counters[key] += 1
        self.last = {
            "outcome": "done" if outcome == "nothing" else outcome,
            "detail": detail,
            "reason": reason,
            "seconds": round(seconds, 3),
            "at": time.time(),
        }
        log_fn = log.warning if outcome in ("failed", "deferred") else log.info
        log_fn("merge (%s) %s in %.2f s: %s", reason, outcome, seconds, detail)
        return self.last

    def _merge(self) -> tuple[str, str]:
        stored = self.received_maps()
        if not stored:
            self._set_global(None)
            return "nothing", "no received maps: the global map is the local map"
        inputs = self.inputs()
        unchanged = inputs is not None and inputs == self._held_inputs
        if self._provisional and self._global is not None and unchanged:
            return self._confirm_settled(stored)
        infos = sorted(((m, peek(m.data)) for m in stored), key=lambda mi: mi[0].vehicle_id)
        for _, info in infos:
            info.check(self.limits)
        local_grid, local_version = self.local_snapshot()
        input_cells = local_grid.size + sum(info.cells for _, info in infos)
        need = SCRATCH_BYTES_PER_CELL * input_cells
        try:
            with self.budget.scratch("merge-scratch", need):
                vids = [m.vehicle_id for m, _ in infos]
                others = [decode_map(m.data, self.limits)[0] for m, _ in infos]
                hints = self._hints(vids)
                hints_only = self._deferred(vids, hints)
                self._deferring = bool(hints_only)
                local_known = local_grid.counts().known
                sizes = [local_known + g.counts().known for g in others]
                contest = self._to_contest(vids, hints, sizes)
                held: set[int] = set()
                kwargs = {}
                if self.confirm_before_fusing:
                    def hold(i: int, r) -> bool:
                        if self._provisional_after(vids[i], r, sizes[i]):
                            held.add(vids[i])
                            return True
                        return False

                    kwargs["hold"] = hold
                if any(hints):
                    kwargs["hints"] = hints
                if hints_only:
                    kwargs["hints_only"] = hints_only
                if contest:
                    kwargs["contest"] = contest
                    self.counters["rechecks"] += len(contest)
                result = self.merge_fn(local_grid, others, self.params, **kwargs)
                del others
                merged = result.global_map
                offsets = {}
                for vid, r in zip(vids, result.results, strict=True):
                    offsets[vid] = {"accepted": bool(r.accepted), "provisional": vid in held,
                                    "score": round(float(r.score), 4),
                                    "reason": str(r.reason), "method": getattr(r, "method", "full"),
                                    **offset_summary(r.transform)}
        except BudgetExceeded as e:
            return "deferred", f"over the memory budget: {e}"
        self._count(result)
        self._confirmations(vids, result.results, held, sizes)
        self._decide(vids, result.results, sizes)
        self._unmerged = {vid for vid, r in zip(vids, result.results, strict=True) if not r.accepted}
        edges = self._remember([m for m, _ in infos], result.results, local_version)
        self._edges = {e.b: e for e in edges}
        self._held_inputs = inputs if held else None
        self._publish([e for e in edges if e.b not in held])
        if not self._install_global(merged):
            return "deferred", f"global map of {merged.size} cells does not fit the memory budget"
        self.offsets = offsets
        accepted = [v for v, o in offsets.items() if in_global_map(o)]
        how = ", ".join(f"{v} {o['method']}{' rechecked' if k in contest else ''}"
                        f"{' provisional' if o['provisional'] else ''}"
                        for k, (v, o) in enumerate(offsets.items()) if o["accepted"] or k in contest)
        rounds = f"{result.rounds} rounds" + (f"; {how}" if how else "")
        return "done", (
            f"{len(accepted)} of {len(infos)} received maps merged {accepted} (local v{local_version}, "
            f"{rounds}); global {'x'.join(map(str, merged.shape))} cells"
        )

    def _confirm_settled(self, stored: list) -> tuple[str, str]:
        """No map changed since the merge that held maps provisional: the pairs settled. A search
        would find the same fits again, so confirm them and fuse them into the global map."""
        held = [m for m in sorted(stored, key=lambda m: m.vehicle_id) if m.vehicle_id in self._provisional]
        grid = self._global[0]
        need = SCRATCH_BYTES_PER_CELL * (grid.size + sum(peek(m.data).cells for m in held))
        threshold = getattr(self.params, "occupied_threshold", OCCUPIED_THRESHOLD)
        try:
            with self.budget.scratch("merge-scratch", need):
                merged = grid.copy()
                for m in held:
                    fuse_transformed(merged, decode_map(m.data, self.limits)[0], self._accepted[m.vehicle_id],
                                     threshold)
        except BudgetExceeded as e:
            return "deferred", f"over the memory budget: {e}"
        if not self._install_global(merged):
            return "deferred", f"global map of {merged.size} cells does not fit the memory budget"
        for m in held:
            self.offsets[m.vehicle_id] = {**self.offsets[m.vehicle_id], "provisional": False}
            log.info("vehicle %d: provisional merge confirmed (no map changed since it was found); fused "
                     "into the global map", m.vehicle_id)
        self._provisional, self._held_inputs = set(), None
        self._publish(list(self._edges.values()))
        return "done", (f"{len(held)} provisional merges confirmed {[m.vehicle_id for m in held]} (no map "
                        f"changed); global {'x'.join(map(str, merged.shape))} cells")

    def _hints(self, vids: list[int]) -> list[list]:
        """Hints per input map: own last accepted transforms, and peers' results when distributed."""
        from coopd.merging.hints import hints_for

        peer = []
        if self.distributed and self.peer_results is not None:
            peer = [r for r in self.peer_results() if r.vehicle_id != self.vehicle_id]
        return hints_for(self.vehicle_id, vids, self._accepted, peer)

    def _deferred(self, vids: list[int], hints: list[list]) -> frozenset[int]:
        """Input maps whose full search waits for a peer: distributed, a lower vehicle id than ours
        holds maps too (it searches, we validate its result: the swarm's merge work drops from
        N(N-1) full searches towards N-1), never merged here, no hint yet, first seen less than
        defer_full_s ago. Bounded: after that we search ourselves."""
        if not (self.distributed and self.defer_full_s > 0 and vids) or min(vids) > self.vehicle_id:
            return frozenset()
        now = time.monotonic()
        out = set()
        for k, vid in enumerate(vids):
            first = self._first_seen.setdefault(vid, now)
            if vid not in self._accepted and not hints[k] and now - first < self.defer_full_s:
                out.add(k)
        return frozenset(out)

    def _to_contest(self, vids: list[int], hints: list[list], sizes: list[int]) -> frozenset[int]:
        """Input maps whose hints compete in a full search this time: contested ones; those whose
        known cells (theirs + ours) grew recheck_growth times since their last decision; and, once
        the pair stopped growing (SETTLED_GROWTH), those decided on maps SETTLED_RECHECK smaller, so
        the transform kept after the flight is judged on the final maps (these two never with
        recheck_growth None)."""
        out = set()
        for k, vid in enumerate(vids):
            if not hints[k]:
                continue
            if vid in self._contested or self._grown_or_settled(vid, sizes[k]):
                out.add(k)
        return frozenset(out)

    def _grown_or_settled(self, vid: int, size: int) -> bool:
        """The pair grew recheck_growth times since its decision, or settled on maps SETTLED_RECHECK
        larger than those it was decided on; never with recheck_growth None."""
        if self.recheck_growth is None:
            return False
        decided = self._decided_at.get(vid, size)
        settled = self._stopped_growing(vid, size) and size > SETTLED_RECHECK * decided
        return size >= self.recheck_growth * decided or settled

    def _stopped_growing(self, vid: int, size: int) -> bool:
        """The pair's known cells grew less than SETTLED_GROWTH since the last merge."""
        return size < SETTLED_GROWTH * self._last_size.get(vid, 0)

    def _provisional_after(self, vid: int, r, size: int) -> bool:
        """Whether vid's accepted result r, on maps of `size` known cells (its and ours), is held out
        of the global map. A new fit from a search is, until the pair stops growing; the same fit
        found again by a recheck on grown (or settled) maps confirms it; our own provisional
        transform, validated alone as a hint, stays provisional until the pair settles; a peer's
        result (peers publish confirmed merges only) is not held."""
        if not self.confirm_before_fusing:
            return False
        from coopd.merging.pair import distinct

        settled = self._stopped_growing(vid, size)
        method = getattr(r, "method", "full")
        if method == "hint:peer":
            return False
        if method != "full":
            return vid in self._provisional and not settled
        before = self._accepted.get(vid)
        if before is None or distinct(before, np.asarray(r.transform, dtype=np.float64)):
            return not settled  # a new fit
        if vid not in self._provisional:
            return False
        return not (settled or self._grown_or_settled(vid, size))

    def _confirmations(self, vids: list[int], results: list, held: set[int], sizes: list[int]) -> None:
        """Log the provisional merges this merge confirmed and keep the set of those still held."""
        for vid, r, size in zip(vids, results, sizes, strict=True):
            if vid in self._provisional and r.accepted and vid not in held:
                log.info("vehicle %d: provisional merge confirmed (%s, maps %.2fx those it was found on); "
                         "fused into the global map", vid, getattr(r, "method", "full"),
                         size / max(1, self._decided_at.get(vid, size)))
        self._provisional = set(held)

    def _decide(self, vids: list[int], results: list, sizes: list[int]) -> None:
        """Record how each map was decided: a full search sets the size mark and settles or raises
        a contest (an ambiguous search also drops our own transform of it); a first hint sets the mark."""
        for k, (vid, r) in enumerate(zip(vids, results, strict=True)):
            self._last_size[vid] = sizes[k]
            method = getattr(r, "method", "full")
            if method == "full":
                self._decided_at[vid] = sizes[k]
                if r.accepted:
                    self._contested.discard(vid)
                elif getattr(r, "ambiguous", False):
                    if vid in self._accepted or vid not in self._contested:
                        log.warning("vehicle %d: its map fits ours two ways (%s); left out until one "
                                    "fit wins", vid, r.reason)
                    self._contested.add(vid)
                    self._accepted.pop(vid, None)
            elif r.accepted:
                self._decided_at.setdefault(vid, sizes[k])

    def on_peer_result(self) -> None:
        """A peer's merge result arrived: merge again if it may bring a map we left out."""
        if self.distributed and self._unmerged:
            self.request("peer result")

    def _count(self, result) -> None:
        """Merge work by kind: full searches, hints accepted (own / peer) and hints refused."""
        methods = [getattr(r, "method", "full") for r in result.results]
        c = self.counters
        c["full_registrations"] += getattr(result, "full_registrations", methods.count("full"))
        c["hinted_own"] += methods.count("hint:own")
        c["hinted_peer"] += methods.count("hint:peer")
        c["hint_rejected"] += sum(getattr(result, "hints_refused", []))

    def _remember(self, stored: list, results: list, local_version: int) -> list[MergeEdge]:
        """Keep every accepted transform as the next merge's own hint; return them as edges."""
        edges = []
        for m, r in zip(stored, results, strict=True):
            if not r.accepted:
                continue
            t = self._accepted[m.vehicle_id] = np.asarray(r.transform, dtype=np.float64)
            full = getattr(r, "method", "full") == "full"
            edges.append(MergeEdge(self.vehicle_id, m.vehicle_id, t, float(np.clip(r.score, 0, 1)),
                                   float(np.clip(getattr(r, "overlap", 0.0), 0, 1)), int(local_version),
                                   int(m.version), EDGE_FULL if full else 0))
        return edges

    def _publish(self, edges: list[MergeEdge]) -> None:
        """Publish our validated merges for peers (only when distributed and there are any)."""
        if not (self.distributed and self.publish_results is not None and edges):
            return
        if not self._changed(edges):
            return
        self._published = {e.b: e.transform for e in edges}
        # increasing across restarts while the clock does: a peer keeps only newer versions
        self._result_version = max(self._result_version + 1, time.time_ns() // 1000)
        try:
            self.publish_results(MergeResultMessage(self.vehicle_id, self._result_version, time.time(),
                                                    tuple(edges[:MAX_EDGES])))
        except ValueError as e:
            log.error("publishing merge results refused: %s", e)

    def _changed(self, edges: list[MergeEdge]) -> bool:
        """Edges differ from the last published: other vehicles, or a transform moved > 2 cm / 0.2 deg."""
        if {e.b for e in edges} != set(self._published):
            return True
        for e in edges:
            old = self._published[e.b]
            moved = float(np.linalg.norm(old[:3, 3] - e.transform[:3, 3]))
            if moved > 0.02 or rotation_angle_deg(old[:3, :3].T @ e.transform[:3, :3]) > 0.2:
                return True
        return False

    def _install_global(self, merged: OccupancyGrid) -> bool:
        """Make merged the global map, with the next version, if the memory budget holds it."""
        if not self.budget.reserve("global", merged.size):
            return False
        version = (self._global[1].version + 1) if self._global is not None else 1
        self._set_global((merged, MapMeta(self.vehicle_id, version, time.time())))
        return True

    def _set_global(self, value) -> None:
        with self._cv:
            self._global = value
        if value is None:
            self.budget.release("global")

    # ---------------------------------------------------------------------------------- reads
    def global_map(self) -> tuple[OccupancyGrid, MapMeta] | None:
        """The last merged global map, or None (then the global map is the local map)."""
        with self._cv:
            return self._global

    def status(self) -> dict:
        if not self.enabled:
            state = "disabled in the configuration"
        elif not self.available:
            state = NOT_AVAILABLE if self.start_error is None else f"merging: off: {self.start_error}"
        else:
            state = "merging" if self.busy_since is not None else "idle"
        return {
            "available": self.available,
            "enabled": self.enabled,
            "state": state,
            "start_error": self.start_error,
            **self.counters,
            "hinted": self.counters["hinted_own"] + self.counters["hinted_peer"],
            "cpu_s": round(self.cpu_s, 3),
            "distributed": self.distributed,
            "last": self.last,
            "offsets": {str(k): v for k, v in self.offsets.items()},
            "contested": sorted(self._contested),
            "provisional": sorted(self._provisional),
            "global_version": None if self._global is None else self._global[1].version,
        }

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

Reading the code: Merger.run is the thread's loop (when to merge: MergeTrigger, skip_as_unchanged);
Merger.merge_once / _merge is one merge step. It is configured by MergerSettings and reads its maps
through MergeSources; what it keeps between merges is owned by coopd.daemon.merge_state (FitBook: a
PairRecord per other vehicle; ResultPublisher; GlobalMapSlot) and every decision on it is a pure
function of coopd.daemon.merge_rules.
"""

import logging
import math
import time
from collections.abc import Callable

import numpy as np

from coopd.daemon import merge_rules as rules
from coopd.daemon.budget import BudgetExceeded, MemoryBudget
from coopd.daemon.merge_state import (
    FitBook,
    GlobalMapSlot,
    MergerSettings,
    MergeSources,
    MergeTrigger,
    ResultPublisher,
)
from coopd.daemon.threads import WorkerProgress
from coopd.grid import OCCUPIED_THRESHOLD, OccupancyGrid, fuse_transformed
from coopd.sharing.wire import MapMeta, MergeEdge, decode_map, peek

log = logging.getLogger("coopd.daemon")

NOT_AVAILABLE = "merging: not available in this build"
PROGRESS_NAME = "merging"
"""The merging thread's name in the watchdog's WorkerProgress."""
BEAT_PERIOD_S = 1.0
"""The idle merging thread wakes at least this often to show it is alive."""
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


def offset_entry(result, held: bool) -> dict:
    """One input map's result as status merges.offsets shows it (held: provisional)."""
    return {"accepted": bool(result.accepted), "provisional": held, "score": round(float(result.score), 4),
            "reason": str(result.reason), "method": rules.method_of(result),
            **offset_summary(result.transform)}


class Merger:
    """The merging thread: run() decides when to merge (MergeTrigger), merge_once() merges; it owns
    the global map (GlobalMapSlot), the per-vehicle fits (FitBook) and the merge counters."""

    def __init__(
        self,
        vehicle_id: int,
        settings: MergerSettings,
        sources: MergeSources,
        budget: MemoryBudget,
        merge_fn: Callable | None = None,
        progress: WorkerProgress | None = None,
        start_error: str | None = None,
    ):
        self.vehicle_id = vehicle_id
        self.settings = settings
        self.sources = sources
        """Both frozen: to change one field, replace the whole (dataclasses.replace), as benches do."""
        self.budget = budget
        self.merge_fn = merge_fn
        """coopd.merging.merge_all, or None in a build without it (find_merge_all)."""
        self.progress = progress if progress is not None else WorkerProgress([PROGRESS_NAME])
        """The merging thread beats here every loop and merges under working() (watchdog health)."""
        self.start_error = start_error
        """Why merging could not start (e.g. an ImportError inside coopd.merging), for status."""
        self.trigger = MergeTrigger()
        self.book = FitBook()
        self.publisher = ResultPublisher(vehicle_id)
        self.global_slot = GlobalMapSlot(vehicle_id, budget)
        self.counters = {"done": 0, "failed": 0, "deferred": 0, "nothing_to_merge": 0, "unchanged": 0,
                         "full_registrations": 0, "hinted_own": 0, "hinted_peer": 0, "hinted_vouched": 0,
                         "hint_rejected": 0, "rechecks": 0}
        self.cpu_s = 0.0
        """CPU time of the merging thread inside merges (time.thread_time): the work the bench sums."""
        self.last: dict | None = None
        """The last merge's outcome, detail, reason, seconds and time."""
        self.offsets: dict[int, dict] = {}
        """Vehicle id -> its map's result at the last merge (offset_entry)."""
        self.busy_since: float | None = None
        self._arrived: set[int] = set()
        """Vehicles whose maps arrived (on_map): a first one is a new map."""
        self._merged_inputs: tuple | None = None
        """inputs() of the last merge done (rules.inputs_to_remember): the same again is skipped."""

    @property
    def available(self) -> bool:
        return self.merge_fn is not None

    # ------------------------------------------------------------------------------- requests
    def request(self, reason: str, urgent: bool = False) -> int:
        """Ask for a merge (non-blocking); returns the request number. Urgent: skip min_gap_s."""
        return self.trigger.request(reason, urgent)

    def on_map(self, vehicle_id: int, version: int) -> None:
        """A received map arrived: merge once the arrivals settled (the first map of a vehicle is a
        new map: more vehicles' first maps are likely still coming, rules.settled_at)."""
        new = vehicle_id not in self._arrived
        self._arrived.add(vehicle_id)
        self.trigger.request(f"map of vehicle {vehicle_id} v{version}", new_map=new)

    def merge_now(self, timeout_s: float) -> dict:
        """Request a merge and wait for its outcome (coopctl merge-now)."""
        if not self.settings.enabled:
            return {"outcome": "failed", "detail": "merging is disabled in the configuration"}
        if not self.available:
            return {"outcome": "failed", "detail": self.status()["state"]}
        ticket = self.request("merge-now", urgent=True)
        done = self.trigger.wait_completed(ticket, timeout_s)
        last = self.last
        if not done or last is None:
            return {"outcome": "queued", "detail": f"merge still running after {timeout_s:.0f} s"}
        return {k: last[k] for k in ("outcome", "detail", "seconds")}

    def on_peer_result(self) -> None:
        """A peer's merge result arrived: merge again if it may bring a map we left out; at once
        (not settled, no minimum gap) while a full search waits for a peer: this is the answer it
        waits for, and validating it costs a fraction of the search it saves."""
        if self.settings.distributed and self.book.left_out:
            self.request("peer result", urgent=self.book.deferring)

    def stop(self) -> None:
        self.trigger.stop()

    # ----------------------------------------------------------------------------------- loop
    def run(self) -> None:
        """Merge every period_s, on request (settled, at most one merge per min_gap_s), at once for
        merge-now; skip a merge whose inputs are those of the last one done."""
        next_periodic = time.monotonic() + self.settings.period_s
        not_before = gap_until = 0.0
        while not self.trigger.stopped:
            due = self.trigger.wait_due(next_periodic, not_before, self.settings,
                                        lambda: self.progress.beat(PROGRESS_NAME), BEAT_PERIOD_S,
                                        self.sources.awaited_maps)
            if due is None:
                return
            ticket, urgent, reasons = due
            if time.monotonic() >= next_periodic:
                next_periodic = time.monotonic() + self.settings.period_s
            if self.settings.enabled and self.available:
                inputs = self.inputs()
                now = time.monotonic()
                if rules.skip_as_unchanged(urgent, inputs, self._merged_inputs, self.book.deferring,
                                           self.book.holding, now >= self.book.defer_until):
                    self.counters["unchanged"] += 1
                    if self.book.deferring:  # merge when the wait for a peer's search is over
                        next_periodic = min(next_periodic, self.book.defer_until)
                elif rules.confirm_too_early(urgent, self.book.holding, inputs, self.book.held_inputs,
                                             now, gap_until):
                    not_before = gap_until  # the maps still change: merge after the usual gap
                    self.request("confirm")
                else:
                    last = self.merge_once(",".join(sorted(set(reasons))))
                    if last["outcome"] == "done":
                        self._merged_inputs = rules.inputs_to_remember(inputs, self.book.left_out)
                    gap_until = time.monotonic() + self.settings.min_gap_s
                    not_before = gap_until
                    if self.book.holding and rules.settled_during(last["seconds"], self.settings.settle_s,
                                                                  inputs, self.inputs()):
                        self.request("confirm", urgent=True)  # no map changed during a long merge
                    elif self.book.holding:  # look again once settled: confirm them, or merge the grown maps
                        not_before = time.monotonic() + min(self.settings.settle_s, self.settings.min_gap_s)
                        self.request("confirm")
            self.trigger.complete(ticket)

    def inputs(self) -> tuple | None:
        """(local version, (vehicle id, version) of every received map, and of every peer's merge
        results when distributed and a map was left out: a new result may merge it); None
        without local_version."""
        src = self.sources
        if src.local_version is None:
            return None
        results = ()
        if self.settings.distributed and src.peer_results is not None and self.book.left_out:
            results = tuple(sorted((r.vehicle_id, r.version) for r in src.peer_results()))
        return (src.local_version(), tuple(sorted((m.vehicle_id, m.version) for m in src.received_maps())),
                results)

    # ------------------------------------------------------------------------------ the merge
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
        """Register and fuse every received map (or confirm the held ones if nothing changed since
        they were held); ("done" | "nothing" | "deferred", detail)."""
        stored = self.sources.received_maps()
        if not stored:
            self.global_slot.clear()
            return "nothing", "no received maps: the global map is the local map"
        inputs = self.inputs()
        has_global = self.global_slot.get() is not None
        if rules.confirms_without_search(self.book.holding, has_global, inputs, self.book.held_inputs):
            return self._confirm_settled(stored)
        s = self.settings
        infos = sorted(((m, peek(m.data)) for m in stored), key=lambda mi: mi[0].vehicle_id)
        for _, info in infos:
            info.check(s.limits)
        local_grid, local_version = self.sources.local_snapshot()
        vids = [m.vehicle_id for m, _ in infos]
        shared_version = self._shared_version(local_version)
        versions = {m.vehicle_id: m.version for m, _ in infos} | {self.vehicle_id: shared_version}
        hints = self._hints(vids, versions)
        alive = frozenset() if self.sources.peers_alive is None else self.sources.peers_alive()
        hints_only = self.book.deferred(self.vehicle_id, vids, hints, s, time.monotonic(), alive)
        if len(hints_only) == len(vids) and not any(hints):
            return self._all_wait([m for m, _ in infos], inputs, shared_version)
        need = SCRATCH_BYTES_PER_CELL * (local_grid.size + sum(info.cells for _, info in infos))
        try:
            with self.budget.scratch("merge-scratch", need):
                others = [decode_map(m.data, s.limits)[0] for m, _ in infos]
                local_known = local_grid.counts().known
                sizes = [local_known + g.counts().known for g in others]
                contest = self.book.to_contest(vids, hints, sizes, s.recheck_growth)
                held: set[int] = set()
                options = self._merge_options(vids, sizes, hints, hints_only, contest, held)
                self.counters["rechecks"] += len(contest)
                result = self.merge_fn(local_grid, others, s.params, **options)
                del others
                merged = result.global_map
                results = zip(vids, result.results, strict=True)
                offsets = {vid: offset_entry(r, vid in held) for vid, r in results}
        except BudgetExceeded as e:
            return "deferred", f"over the memory budget: {e}"
        self._count(result)
        edges = self.book.record(self.vehicle_id, [m for m, _ in infos], result.results, sizes, held, inputs,
                                 shared_version)
        self._publish([e for e in edges if e.b not in held])
        if not self.global_slot.install(merged):
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

    def _all_wait(self, maps: list, inputs: tuple | None, shared_version: int) -> tuple[str, str]:
        """Every map's search waits for a peer and none has a hint: the merge would fuse nothing, so the
        maps are not even decoded (at 30 drones, 29 drones each decoded 29 maps for nothing while the
        first maps were still being exchanged). Booked as merge_all would report it."""
        from coopd.merging.multi import waiting_result  # only merging with merge_all: the build has it

        waiting = waiting_result()
        results = [waiting] * len(maps)
        sizes = [self.book.pair(m.vehicle_id).last_size for m in maps]  # unchanged: nothing was measured
        self.book.record(self.vehicle_id, maps, results, sizes, set(), inputs, shared_version)
        self._publish([])
        self.global_slot.clear()
        self.offsets = {m.vehicle_id: offset_entry(waiting, False) for m in maps}
        return "done", (f"0 of {len(maps)} received maps merged [] (each waits for the result of a lower "
                        f"vehicle id, alive in the swarm); the global map is the local map")

    def _merge_options(self, vids: list[int], sizes: list[int], hints: list[list], hints_only: frozenset[int],
                       contest: frozenset[int], held: set[int]) -> dict:
        """merge_all's keyword arguments, each only when it says something: hold (with
        confirm_before_fusing: FitBook.holds, collecting the held vehicle ids in `held`; then also
        the searches that may run ahead, FitBook.holds_any_fit, on search_threads), hints,
        hints_only (searches deferred to a peer) and contest (maps rechecked)."""
        options = {}
        if self.settings.confirm_before_fusing:
            recheck_growth = self.settings.recheck_growth

            def hold(i: int, r) -> bool:
                if self.book.holds(vids[i], r, sizes[i], recheck_growth):
                    held.add(vids[i])
                    return True
                return False

            options["hold"] = hold
            if self.settings.search_threads > 1:
                options["ahead"] = lambda i: self.book.holds_any_fit(vids[i], sizes[i])
                options["workers"] = self.settings.search_threads
        if any(hints):
            options["hints"] = hints
        if hints_only:
            options["hints_only"] = hints_only
        if contest:
            options["contest"] = contest
        return options

    def _confirm_settled(self, stored: list) -> tuple[str, str]:
        """No map changed since the merge that held maps provisional: the pairs settled. A search
        would find the same fits again, so confirm them and fuse them into the global map."""
        provisional = set(self.book.provisional())
        held = [m for m in sorted(stored, key=lambda m: m.vehicle_id) if m.vehicle_id in provisional]
        grid = self.global_slot.get()[0]
        need = SCRATCH_BYTES_PER_CELL * (grid.size + sum(peek(m.data).cells for m in held))
        threshold = getattr(self.settings.params, "occupied_threshold", OCCUPIED_THRESHOLD)
        try:
            with self.budget.scratch("merge-scratch", need):
                merged = grid.copy()
                for m in held:
                    fuse_transformed(merged, decode_map(m.data, self.settings.limits)[0],
                                     self.book.pair(m.vehicle_id).transform, threshold)
        except BudgetExceeded as e:
            return "deferred", f"over the memory budget: {e}"
        if not self.global_slot.install(merged):
            return "deferred", f"global map of {merged.size} cells does not fit the memory budget"
        for m in held:
            self.offsets[m.vehicle_id] = {**self.offsets[m.vehicle_id], "provisional": False}
            log.info("vehicle %d: provisional merge confirmed (no map changed since it was found); fused "
                     "into the global map", m.vehicle_id)
        self.book.confirm_all()
        self._publish(self.book.edges())
        return "done", (f"{len(held)} provisional merges confirmed {[m.vehicle_id for m in held]} (no map "
                        f"changed); global {'x'.join(map(str, merged.shape))} cells")

    def _shared_version(self, local_version: int) -> int:
        """Our local map's version as peers hold it (what our edges name)."""
        to_shared = self.sources.published_version
        return local_version if to_shared is None else to_shared(local_version)

    def _hints(self, vids: list[int], versions: dict[int, int]) -> list[list]:
        """Hints per input map: own last accepted transforms, and peers' results when distributed
        (versions: the map version we hold per vehicle, ours included, to tell vouched edges)."""
        from coopd.merging.hints import hints_for  # only merging with merge_all: the build has it

        peer = []
        if self.settings.distributed and self.sources.peer_results is not None:
            peer = [r for r in self.sources.peer_results() if r.vehicle_id != self.vehicle_id]
        return hints_for(self.vehicle_id, vids, self.book.transforms(), peer,
                         versions if self.settings.vouched else None)

    def _count(self, result) -> None:
        """Merge work by kind: full searches, hints accepted (own / peer) and hints refused."""
        methods = [rules.method_of(r) for r in result.results]
        c = self.counters
        c["full_registrations"] += getattr(result, "full_registrations", methods.count("full"))
        c["hinted_own"] += methods.count("hint:own")
        c["hinted_peer"] += methods.count("hint:peer")
        c["hint_rejected"] += sum(getattr(result, "hints_refused", []))
        c["hinted_vouched"] += getattr(result, "vouched", 0)
        self.cpu_s += getattr(result, "worker_cpu_s", 0.0)  # searches run on worker threads

    def _publish(self, edges: list[MergeEdge]) -> None:
        """Publish our validated merges for peers (only when distributed and they changed)."""
        send = self.sources.publish_results
        if self.settings.distributed and send is not None:
            self.publisher.publish(edges, send)

    # ---------------------------------------------------------------------------------- reads
    def global_map(self) -> tuple[OccupancyGrid, MapMeta] | None:
        """The last merged global map, or None (then the global map is the local map)."""
        return self.global_slot.get()

    def status(self) -> dict:
        if not self.settings.enabled:
            state = "disabled in the configuration"
        elif not self.available:
            state = NOT_AVAILABLE if self.start_error is None else f"merging: off: {self.start_error}"
        else:
            state = "merging" if self.busy_since is not None else "idle"
        return {
            "available": self.available,
            "enabled": self.settings.enabled,
            "state": state,
            "start_error": self.start_error,
            **self.counters,
            "hinted": self.counters["hinted_own"] + self.counters["hinted_peer"],
            "cpu_s": round(self.cpu_s, 3),
            "distributed": self.settings.distributed,
            "last": self.last,
            "offsets": {str(k): v for k, v in self.offsets.items()},
            "contested": self.book.contested(),
            "provisional": self.book.provisional(),
            "global_version": self.global_slot.version,
        }

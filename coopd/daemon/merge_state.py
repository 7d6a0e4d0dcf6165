"""What the merging thread (coopd.daemon.merger) is configured with, reads from, and keeps between
merges, each owned by one small class:

- MergerSettings: the [merging] configuration, frozen, built once (MergerSettings.from_config);
- MergeSources: the callables it reads the maps from and publishes its results through;
- MergeTrigger: merge requests and the clock deciding when the thread merges (thread-safe);
- FitBook: one PairRecord per other vehicle (its accepted transform, when it was decided, whether it
  is contested, provisional, left out) and the rules of coopd.daemon.merge_rules applied to them;
- ResultPublisher: our merge results as published to peers (only when they changed);
- GlobalMapSlot: the last global map, its version and its memory reservation (thread-safe).
"""

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from coopd.daemon import merge_rules as rules
from coopd.daemon.budget import MemoryBudget
from coopd.grid import OccupancyGrid
from coopd.sharing.wire import DEFAULT_LIMITS, MAX_EDGES, DecodeLimits, MapMeta, MergeEdge, MergeResultMessage

log = logging.getLogger("coopd.daemon")

MERGE_MIN_GAP_S = 5.0
"""Maps arriving faster than this (peers publish every second) are merged together, not one by one.
A received map also waits until no other arrived for one discovery scan period (the peers found in a
scan deliver within it), so the maps of a swarm's first exchange merge in one go (settle_s)."""


@dataclass(frozen=True)
class MergerSettings:
    """How the merging thread merges; the daemon builds it from the configuration (from_config)."""

    period_s: float
    """Merge at least this often (a merge with unchanged inputs is skipped)."""
    enabled: bool = True
    params: Any = None
    """coopd.merging.MergeParams for merge_all (None: its defaults)."""
    limits: DecodeLimits = DEFAULT_LIMITS
    """Limits every received map is checked against before it is decoded."""
    min_gap_s: float = 0.0
    """Received maps trigger a merge at most this often (a peer publishes every second)."""
    settle_s: float = 0.0
    """A requested merge waits until no request came for this long (the maps of a sharing burst
    merge together, not the first one alone), but at most max(settle_s, min_gap_s), or a few times
    that while vehicles' first maps keep arriving (merge_rules.settled_at)."""
    distributed: bool = True
    """Use peers' merge results as hints and publish ours; off: own warm start only."""
    defer_full_s: float = 0.0
    """Distributed: a map's full search waits this long for the swarm's lowest vehicle id to
    publish it (then validating its result is enough); 0: never wait."""
    vouched: bool = True
    """Distributed: a peer's edge found on exactly the map versions we hold is checked, not refined
    (coopd.merging.hints, vouched hints)."""
    search_threads: int = 1
    """With confirm_before_fusing: full searches of maps whose fit would be held run this many at a
    time (merge_all ahead/workers)."""
    recheck_growth: float | None = 1.3
    """A merged map is searched again, its known transforms competing, once the known cells of it
    and our map grew this much since it was last decided: a transform accepted on small early maps
    of a symmetric building (a 180-degree flip, a slide along a corridor) is not kept for good.
    None: never re-searched, neither grown nor settled (the rules before rechecks, for benches);
    contested maps still only compete."""
    confirm_before_fusing: bool = False
    """A fit newly found by a search stays out of the global map (provisional) until a recheck on
    maps recheck_growth times larger finds it again or the pair stops growing."""

    @classmethod
    def from_config(cls, config, params=None) -> "MergerSettings":
        """The daemon's settings: [merging], received maps within [sharing]'s limits, requests
        settled for one discovery scan and merged at most every MERGE_MIN_GAP_S (or period_s)."""
        merging = config.merging
        return cls(
            period_s=merging.period_s,
            enabled=merging.enabled,
            params=params,
            limits=DecodeLimits(config.sharing.max_map_cells, config.sharing.max_map_bytes),
            min_gap_s=min(merging.period_s, MERGE_MIN_GAP_S),
            settle_s=min(config.sharing.scan_period_s, MERGE_MIN_GAP_S),
            distributed=merging.distributed,
            defer_full_s=merging.defer_full_s,
            vouched=merging.vouched,
            search_threads=merging.search_threads,
            recheck_growth=merging.recheck_growth,
            confirm_before_fusing=merging.confirm_before_fusing,
        )


@dataclass(frozen=True)
class MergeSources:
    """What the merging thread reads and where its results go, as callables."""

    local_snapshot: Callable[[], tuple[OccupancyGrid, int]]
    """A copy of the local map and its version."""
    received_maps: Callable[[], list]
    """The received maps at rest (vehicle_id, version, data: the encoded map)."""
    local_version: Callable[[], int] | None = None
    """The local map's version without copying it; given, a merge whose inputs (this and every
    received map's version) equal those of the last merge done is skipped, counted "unchanged"."""
    peer_results: Callable[[], list] | None = None
    """Peers' merge results (wire.MergeResultMessage), used as hints when distributed."""
    publish_results: Callable[[MergeResultMessage], None] | None = None
    """Hands our merge results to sharing, when distributed."""
    awaited_maps: Callable[[], int] | None = None
    """How many peers known alive have not sent their map yet (a first merge waits for them, within
    merge_rules.NEW_MAPS_WAIT gaps); None: none is ever awaited."""
    peers_alive: Callable[[], frozenset[int]] | None = None
    """Vehicle ids of the peers known alive (a lower one than ours searches: we wait for its result);
    None: only the maps held count."""
    published_version: Callable[[int], int] | None = None
    """The version peers hold of our local map at a given version counter (the version our edges
    name, so a peer can tell it merged the very maps we did); None: the counter itself."""


class MergeTrigger:
    """Merge requests and when the merging thread acts on them: every period_s, on request once the
    requests settled (settle_s) and at most once per min_gap_s, at once when urgent (merge-now).
    Requests arriving during a merge are served by the next one; merge_now waits for its ticket."""

    def __init__(self):
        self._cv = threading.Condition()
        self._stop = threading.Event()
        self.requested = 0
        """Requests numbered so far (the last ticket handed out)."""
        self._completed = 0
        self._urgent = False
        self._reasons: list[str] = []
        self._pending_since: float | None = None
        self._last_request_at = 0.0
        self._last_new_at: float | None = None

    @property
    def stopped(self) -> bool:
        return self._stop.is_set()

    def request(self, reason: str, urgent: bool = False, new_map: bool = False) -> int:
        """Ask for a merge (non-blocking); returns the request's ticket. Urgent: skip min_gap_s.
        new_map: it brings the map of a vehicle never merged (rules.settled_at waits longer)."""
        with self._cv:
            self.requested += 1
            self._urgent |= urgent
            self._last_request_at = time.monotonic()
            if self._pending_since is None:
                self._pending_since = self._last_request_at
            if new_map:
                self._last_new_at = self._last_request_at
            if len(self._reasons) < 16:
                self._reasons.append(reason)
            self._cv.notify_all()
            return self.requested

    def stop(self) -> None:
        self._stop.set()
        with self._cv:
            self._cv.notify_all()

    def wait_due(self, next_periodic: float, not_before: float, settings: MergerSettings,
                 beat: Callable[[], None], beat_period_s: float,
                 awaited: Callable[[], int] | None = None) -> tuple[int, bool, list[str]] | None:
        """Block until a merge is due: an urgent request, pending requests settled and not before
        `not_before`, or with none pending the period (`next_periodic`). Calls beat() at least every
        beat_period_s; awaited() (maps still coming, rules.settled_at) is asked outside the trigger's
        lock, since it reads the sharing layer, which requests merges under its own locks.
        Returns (ticket served, urgent, reasons) and clears them; None once stopped."""
        while not self._stop.is_set():
            beat()
            awaiting = awaited is not None and self._last_new_at is not None and awaited() > 0
            with self._cv:
                now = time.monotonic()
                pending = self.requested > self._completed
                settled = rules.settled_at(self._pending_since, self._last_request_at, settings.settle_s,
                                           settings.min_gap_s, self._last_new_at, awaiting)
                # pending requests are served once settled (bounded by rules.settled_at), the period
                # only when none pends: it must not cut short the wait for a swarm's first maps
                due = max(not_before, settled) if pending else next_periodic
                if self._urgent or now >= due:
                    self._pending_since = self._last_new_at = None
                    urgent, self._urgent = self._urgent, False
                    reasons, self._reasons = self._reasons or ["period"], []
                    return self.requested, urgent, reasons
                self._cv.wait(min(beat_period_s, max(0.0, due - now)))
        return None

    def complete(self, ticket: int) -> None:
        """Every request up to `ticket` is served."""
        with self._cv:
            self._completed = max(self._completed, ticket)
            self._cv.notify_all()

    def wait_completed(self, ticket: int, timeout_s: float) -> bool:
        """Wait until request `ticket` is served (or the thread stops); False on timeout."""
        with self._cv:
            return self._cv.wait_for(lambda: self._completed >= ticket or self._stop.is_set(), timeout_s)


@dataclass
class PairRecord:
    """What the merging thread keeps about one other vehicle's map and ours (a pair)."""

    transform: np.ndarray | None = None
    """Last accepted transform of its map frame into ours: the next merge's own hint."""
    decided_at: int | None = None
    """Known cells of the pair when its transform was last decided (a search, or a first hint)."""
    last_size: int = 0
    """Known cells of the pair at the last merge (to see the maps settle)."""
    contested: bool = False
    """Its last full search found two fits (ambiguous): its hints only compete."""
    provisional: bool = False
    """Its accepted transform is provisional: reported, held out of the global map, not published."""
    left_out: bool = False
    """The last merge left its map out (refused or deferred)."""
    edge: MergeEdge | None = None
    """The edge of its accepted transform at the last merge (published once confirmed)."""
    first_seen: float | None = None
    """When a full search of its map first waited for a peer (monotonic clock)."""

    def decided_or(self, size: int) -> int:
        """decided_at, or `size` for a pair never decided (nothing to recheck yet)."""
        return size if self.decided_at is None else self.decided_at


class FitBook:
    """The merging thread's per-vehicle book-keeping (a PairRecord each) and the decisions read from
    it: hints, rechecks, deferrals, provisional fits. Used by the merging thread only."""

    def __init__(self):
        self._pairs: dict[int, PairRecord] = {}
        self.deferring = False
        """The last merge left a map's full search to a peer: merge again on the period even if
        nothing changed, so that the search runs here once defer_full_s is over."""
        self.defer_until = 0.0
        """When the first search left to a peer stops waiting (monotonic; 0: none waits)."""
        self.held_inputs: tuple | None = None
        """Inputs of the merge that left maps provisional: the same again means they settled."""

    def pair(self, vid: int) -> PairRecord:
        """vid's record (a new, empty one for a vehicle never seen)."""
        return self._pairs.setdefault(vid, PairRecord())

    # ------------------------------------------------------- reads (status and sharing threads too)
    def _records(self) -> list[tuple[int, PairRecord]]:
        """The records, copied in one step (list() of a dict view runs without yielding the GIL): other
        threads read while the merging thread adds records."""
        return list(self._pairs.items())

    def transforms(self) -> dict[int, np.ndarray]:
        """Vehicle id -> last accepted transform (the own hints)."""
        return {vid: p.transform for vid, p in self._records() if p.transform is not None}

    def contested(self) -> list[int]:
        return sorted(vid for vid, p in self._records() if p.contested)

    def provisional(self) -> list[int]:
        return sorted(vid for vid, p in self._records() if p.provisional)

    @property
    def holding(self) -> bool:
        """Some accepted fit is provisional (held out of the global map)."""
        return any(p.provisional for _, p in self._records())

    @property
    def left_out(self) -> bool:
        """The last merge left some map out: a peer's new result may merge it."""
        return any(p.left_out for _, p in self._records())

    def edges(self) -> list[MergeEdge]:
        """The edges of the last merge's accepted transforms, in vehicle id order."""
        return [p.edge for _, p in sorted(self._records()) if p.edge is not None]

    # ------------------------------------------------------------------------- before a merge
    def deferred(self, own_id: int, vids: list[int], hints: list[list], settings: MergerSettings,
                 now: float, alive: frozenset[int] = frozenset()) -> frozenset[int]:
        """Positions of the input maps whose full search waits for a peer (merge_all hints_only);
        remembers when each map first waited, and whether any does (deferring). alive: the vehicle
        ids of the peers known alive (MergeSources.peers_alive)."""
        out = set()
        until = []
        if rules.waits_for_peer(own_id, vids, settings.distributed, settings.defer_full_s, alive):
            for k, vid in enumerate(vids):
                p = self.pair(vid)
                if p.first_seen is None:
                    p.first_seen = now
                if rules.defers_search(p.transform is not None, bool(hints[k]), now - p.first_seen,
                                       settings.defer_full_s):
                    out.add(k)
                    until.append(p.first_seen + settings.defer_full_s)
        self.deferring = bool(out)
        self.defer_until = min(until, default=0.0)
        return frozenset(out)

    def to_contest(self, vids: list[int], hints: list[list], sizes: list[int],
                   recheck_growth: float | None) -> frozenset[int]:
        """Positions of the input maps whose hints compete in a full search this time (merge_all
        contest): contested ones, and those due for a recheck (rules.due_for_recheck)."""
        out = set()
        for k, vid in enumerate(vids):
            p = self._pairs.get(vid, PairRecord())
            if rules.competes(bool(hints[k]), p.contested, self._due(p, sizes[k], recheck_growth)):
                out.add(k)
        return frozenset(out)

    def holds(self, vid: int, result, size: int, recheck_growth: float | None) -> bool:
        """Whether vid's accepted result, on a pair of `size` known cells, is held out of the global
        map (rules.held_provisional); asked by merge_all (hold=...) during the merge."""
        p = self._pairs.get(vid, PairRecord())
        method = rules.method_of(result)
        new_fit = method == "full" and _new_fit(p.transform, result.transform)
        settled = rules.stopped_growing(size, p.last_size)
        due = self._due(p, size, recheck_growth)
        return rules.held_provisional(method, new_fit, p.provisional, settled, due)

    def holds_any_fit(self, vid: int, size: int) -> bool:
        """Whether any accepted full-search result of vid's map would be held (holds): a pair never
        fitted, still growing, takes its first fit as a new one and holds it until it settles."""
        p = self._pairs.get(vid, PairRecord())
        return p.transform is None and not rules.stopped_growing(size, p.last_size)

    @staticmethod
    def _due(p: PairRecord, size: int, recheck_growth: float | None) -> bool:
        return rules.due_for_recheck(size, p.decided_or(size), p.last_size, recheck_growth)

    # -------------------------------------------------------------------------- after a merge
    def record(self, own_id: int, maps: list, results: list, sizes: list[int], held: set[int],
               inputs: tuple | None, local_version: int) -> list[MergeEdge]:
        """Book a merge's results (maps: the received maps merged, in merge order; local_version: our
        map's version as peers hold it): confirm or hold provisional fits, record how each map was
        decided, keep every accepted transform as the next merge's own hint. Returns the edges of the
        accepted transforms."""
        vids = [m.vehicle_id for m in maps]
        self._confirm(vids, results, held, sizes)
        self._decide(vids, results, sizes)
        edges = {}
        for m, r in zip(maps, results, strict=True):
            p = self.pair(m.vehicle_id)
            p.left_out = not r.accepted
            if r.accepted:
                edges[m.vehicle_id] = rules.merge_edge(own_id, m.vehicle_id, m.version, local_version, r)
                p.transform = edges[m.vehicle_id].transform
        for vid, p in self._pairs.items():
            p.edge = edges.get(vid)
            p.left_out = p.left_out and vid in vids
        self.held_inputs = inputs if held else None
        return list(edges.values())

    def confirm_all(self) -> list[int]:
        """Every provisional fit is confirmed (the maps settled); returns their vehicle ids."""
        held = self.provisional()
        for vid in held:
            self._pairs[vid].provisional = False
        self.held_inputs = None
        return held

    def _confirm(self, vids: list[int], results: list, held: set[int], sizes: list[int]) -> None:
        """Log the provisional fits this merge confirmed; the held ones are now the provisional ones."""
        for vid, r, size in zip(vids, results, sizes, strict=True):
            p = self._pairs.get(vid)
            if p is not None and p.provisional and r.accepted and vid not in held:
                grown = size / max(1, p.decided_or(size))
                log.info("vehicle %d: provisional merge confirmed (%s, maps %.2fx those it was found on); "
                         "fused into the global map", vid, rules.method_of(r), grown)
        for vid, p in self._pairs.items():
            p.provisional = vid in held
        for vid in held:
            self.pair(vid).provisional = True

    def _decide(self, vids: list[int], results: list, sizes: list[int]) -> None:
        """Record how each map was decided: a full search sets the size mark and settles or raises
        a contest (an ambiguous search also drops our own transform of it); a first hint sets the mark."""
        for vid, r, size in zip(vids, results, sizes, strict=True):
            p = self.pair(vid)
            p.last_size = size
            if rules.method_of(r) == "full":
                p.decided_at = size
                if r.accepted:
                    p.contested = False
                elif getattr(r, "ambiguous", False):
                    if p.transform is not None or not p.contested:
                        log.warning("vehicle %d: its map fits ours two ways (%s); left out until one "
                                    "fit wins", vid, r.reason)
                    p.contested = True
                    p.transform = None
            elif r.accepted and p.decided_at is None:
                p.decided_at = size


def _new_fit(before: np.ndarray | None, transform) -> bool:
    """No fit before, or a distinct one (coopd.merging.pair.distinct: > 5 deg or > 1 m apart)."""
    if before is None:
        return True
    from coopd.merging.pair import distinct  # only called from within merge_all: the build has it

    return distinct(before, np.asarray(transform, dtype=np.float64))


class ResultPublisher:
    """Our merge results as published to peers: a new version only when the edges changed
    (rules.edges_changed), versions increasing across restarts while the clock does."""

    def __init__(self, vehicle_id: int):
        self.vehicle_id = vehicle_id
        self._published: dict[int, np.ndarray] = {}
        """Vehicle id -> transform we last published."""
        self._version = 0

    def publish(self, edges: list[MergeEdge], send: Callable[[MergeResultMessage], None]) -> None:
        """Send edges as a new merge-result message unless they are those published last."""
        if not edges or not rules.edges_changed(self._published, edges):
            return
        self._published = {e.b: e.transform for e in edges}
        # increasing across restarts while the clock does: a peer keeps only newer versions
        self._version = max(self._version + 1, time.time_ns() // 1000)
        try:
            send(MergeResultMessage(self.vehicle_id, self._version, time.time(), tuple(edges[:MAX_EDGES])))
        except ValueError as e:
            log.error("publishing merge results refused: %s", e)


class GlobalMapSlot:
    """The last merged global map and its version, reserved in the memory budget ("global");
    written by the merging thread, read by any."""

    def __init__(self, vehicle_id: int, budget: MemoryBudget):
        self.vehicle_id = vehicle_id
        self.budget = budget
        self._lock = threading.Lock()
        self._value: tuple[OccupancyGrid, MapMeta] | None = None

    def get(self) -> tuple[OccupancyGrid, MapMeta] | None:
        with self._lock:
            return self._value

    @property
    def version(self) -> int | None:
        value = self.get()
        return None if value is None else value[1].version

    def install(self, merged: OccupancyGrid) -> bool:
        """Make merged the global map, with the next version, if the memory budget holds it."""
        if not self.budget.reserve("global", merged.size):
            return False
        with self._lock:
            version = (self._value[1].version + 1) if self._value is not None else 1
            self._value = (merged, MapMeta(self.vehicle_id, version, time.time()))
        return True

    def clear(self) -> None:
        """No global map (it is the local map): its reservation is released."""
        with self._lock:
            self._value = None
        self.budget.release("global")

"""The merging thread's rules as pure functions: when a merge runs, which maps are searched again,
which fits stay provisional, which full searches wait for a peer, what is published.

Sizes are the known cells of a pair (the received map's and ours) at a merge. The state these rules
read (per-vehicle records, the trigger's clock) is owned by coopd.daemon.merge_state; the merging
thread (coopd.daemon.merger) applies the rules to it. Nothing here locks, sleeps or logs.
"""

from collections.abc import Iterable

import numpy as np

from coopd.geometry import rotation_angle_deg
from coopd.sharing.wire import EDGE_FULL, MergeEdge

SETTLED_GROWTH = 1.01
"""A pair whose known cells grew less than this since the last merge has settled (the flight is over)."""
SETTLED_RECHECK = 1.05
"""A settled pair decided on maps this much smaller is searched once more, on the final maps."""
PUBLISH_SHIFT_M = 0.02
PUBLISH_TURN_DEG = 0.2
"""A published transform is published again only once it moved more than this."""


def method_of(result) -> str:
    """How merge_all found a result: "full" (a search), "hint:own" or "hint:peer"."""
    return getattr(result, "method", "full")


# ---------------------------------------------------------------------------------- triggering
NEW_MAPS_WAIT = 3
"""While maps of vehicles never merged keep arriving, or peers known alive have not sent theirs yet,
pending requests settle for up to this many times max(settle_s, min_gap_s) after the first: a
swarm's first exchange is searched in one merge."""


def settled_at(pending_since: float | None, last_request_at: float, settle_s: float,
               min_gap_s: float, last_new_at: float | None = None, awaiting: bool = False) -> float:
    """When pending merge requests have settled: settle_s after the last one, but at most
    max(settle_s, min_gap_s) after the first (maps that never stop still merge); 0 when none pends.

    When a pending request brought the map of a vehicle never seen before (`last_new_at`, the
    latest such), they settle settle_s after the last new map, or while peers known alive have not
    sent theirs (`awaiting`) until they do, in either case at most NEW_MAPS_WAIT times the usual cap
    after the first: at 30 drones the first exchange takes longer than min_gap_s, and a merge that
    starts before the last maps arrived searches and confirms them in groups, each group making
    every peer merge again."""
    if pending_since is None:
        return 0.0
    gap = max(settle_s, min_gap_s)
    due = min(last_request_at + settle_s, pending_since + gap)
    if last_new_at is not None:
        cap = pending_since + NEW_MAPS_WAIT * gap
        due = max(due, cap if awaiting else min(last_new_at + settle_s, cap))
    return due


def skip_as_unchanged(urgent: bool, inputs: tuple | None, last_inputs: tuple | None, deferring: bool,
                      holding: bool, deferral_over: bool = True) -> bool:
    """Whether a merge is skipped (counted "unchanged"): merging is deterministic, so inputs equal to
    those of the last merge done would rebuild the same global map. Never when urgent (merge-now),
    nor once a full search that waited for a peer is due to run here (deferring, and its wait is
    over), nor while fits are provisional (the next merge confirms them). While the wait lasts, a
    merge on unchanged inputs would do nothing the last did not (a peer's new result changes them):
    at 30 drones those idle merges of 29 waiting drones took the lowest id's CPU for its searches."""
    same = inputs is not None and inputs == last_inputs
    return not urgent and same and not (deferring and deferral_over) and not holding


def confirm_too_early(urgent: bool, holding: bool, inputs: tuple | None, held_inputs: tuple | None,
                      now: float, gap_until: float) -> bool:
    """Whether a merge due before the usual gap (min_gap_s after the last) waits for it: fits held
    provisional are looked at again one settling period (settle_s) after the merge that held them,
    to be confirmed if no input changed since; if some did (the maps still grow), the merge waits
    for the gap as any other. Never when urgent."""
    return not urgent and holding and inputs != held_inputs and now < gap_until


def settled_during(merge_s: float, settle_s: float, inputs_before: tuple | None,
                   inputs_after: tuple | None) -> bool:
    """Whether the maps settled during a merge: it lasted at least settle_s and no input changed
    meanwhile. Fits it held provisional are then confirmed at once, not one settling period later
    (at 30 drones the lowest id's first merge lasts tens of seconds, and every other drone waits
    for its result)."""
    return inputs_before is not None and merge_s >= settle_s and inputs_before == inputs_after


def inputs_to_remember(inputs: tuple | None, left_out: bool) -> tuple | None:
    """The inputs a done merge is remembered by: with no map left out, peers' results no longer
    count (a new one cannot merge anything more), so they are dropped from the comparison."""
    if inputs is not None and not left_out:
        return (*inputs[:2], ())
    return inputs


def confirms_without_search(holding: bool, has_global: bool, inputs: tuple | None,
                            held_inputs: tuple | None) -> bool:
    """Whether provisional fits are confirmed without searching: no input changed since the merge
    that held them (the maps settled), and a search would find the same fits again."""
    return holding and has_global and inputs is not None and inputs == held_inputs


# ----------------------------------------------------------------------------- pair decisions
def stopped_growing(size: int, last_size: int) -> bool:
    """The pair's known cells grew less than SETTLED_GROWTH since the last merge (0: never merged)."""
    return size < SETTLED_GROWTH * last_size


def due_for_recheck(size: int, decided_at: int, last_size: int, recheck_growth: float | None) -> bool:
    """Whether a pair decided on maps of `decided_at` known cells is searched again at `size`: it grew
    recheck_growth times, or it stopped growing on maps SETTLED_RECHECK larger than those it was
    decided on (the transform kept after the flight is judged on the final maps). Never with
    recheck_growth None."""
    if recheck_growth is None:
        return False
    settled = stopped_growing(size, last_size) and size > SETTLED_RECHECK * decided_at
    return size >= recheck_growth * decided_at or settled


def competes(has_hints: bool, contested: bool, due: bool) -> bool:
    """Whether a map's hints compete in a full search instead of being judged alone: a map with hints
    that is contested (its last search found two fits) or due for a recheck."""
    return has_hints and (contested or due)


def held_provisional(method: str, new_fit: bool, was_provisional: bool, settled: bool, due: bool) -> bool:
    """Whether an accepted fit is held out of the global map (provisional), with confirm_before_fusing.

    A peer's result is never held (peers publish confirmed merges only). Our own transform validated
    alone as a hint stays as it was until the pair settles. A search's new fit (none before, or a
    distinct one) is held until the pair settles; finding the same fit again confirms it once the
    pair grew (a recheck, `due`) or settled."""
    if method == "hint:peer":
        return False
    if method != "full":
        return was_provisional and not settled
    if new_fit:
        return not settled
    if not was_provisional:
        return False
    return not (settled or due)


def waits_for_peer(own_id: int, vids: list[int], distributed: bool, defer_full_s: float,
                   alive: Iterable[int] = ()) -> bool:
    """Whether full searches may wait for a peer at all: distributed, a wait set, and a lower vehicle
    id than ours in the swarm, among the maps we hold (vids) or the peers known alive, their maps come
    or not (it searches, we validate its result: the swarm's merge work drops from N(N-1) full
    searches towards N-1). Counting only the maps held, a drone that had received a few maps of
    higher ids first searched them itself, and its partial results made every other drone merge
    again."""
    return distributed and defer_full_s > 0 and bool(vids) and min([*vids, *alive]) < own_id


def defers_search(merged_before: bool, has_hints: bool, waited_s: float, defer_full_s: float) -> bool:
    """Whether one map's full search waits for a peer: never merged here, no hint yet, first seen less
    than defer_full_s ago (bounded: after that we search ourselves)."""
    return not merged_before and not has_hints and waited_s < defer_full_s


# ---------------------------------------------------------------------------------- publishing
def merge_edge(own_id: int, vid: int, map_version: int, local_version: int, result) -> MergeEdge:
    """An accepted result as the edge we publish: our frame <- vid's, with its score and overlap
    clipped to [0, 1], both maps' versions, and whether a full search found it."""
    overlap = getattr(result, "overlap", 0.0)
    return MergeEdge(own_id, vid, np.asarray(result.transform, dtype=np.float64),
                     float(np.clip(result.score, 0, 1)), float(np.clip(overlap, 0, 1)),
                     int(local_version), int(map_version), EDGE_FULL if method_of(result) == "full" else 0)


def edges_changed(published: dict[int, np.ndarray], edges: list[MergeEdge]) -> bool:
    """Whether edges differ from the transforms last published (vehicle id -> transform): other
    vehicles, or a transform moved more than PUBLISH_SHIFT_M / PUBLISH_TURN_DEG. An unchanged set is
    not published again: a new version makes every peer merge again, and their answers us."""
    if {e.b for e in edges} != set(published):
        return True
    for e in edges:
        old = published[e.b]
        moved = float(np.linalg.norm(old[:3, 3] - e.transform[:3, 3]))
        turned = rotation_angle_deg(old[:3, :3].T @ e.transform[:3, :3])
        if moved > PUBLISH_SHIFT_M or turned > PUBLISH_TURN_DEG:
            return True
    return False

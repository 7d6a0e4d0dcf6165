"""Hinted merging (thesis §1, §10.4: drones share the parameters of merges already computed).

A hint is a candidate transform for one input map, from our own last accepted merge of that map
("own": map frames are odometry frames, they do not move) or from a peer's published merge result
("peer"). A hint is refined by ICP and must pass the same validation thresholds as a full merge
(min_inliers, min_agreement, min_overlap, min_score, pair.judge); if none passes, the caller runs
the full search. A hint costs one ICP + one validation instead of levelling, the yaw search and
several refinements.

No runner-up margin is checked for a hint. The margin guards the *choice* among the search's
hypotheses in repeated structure; a hint is not chosen among alternatives here, it comes from a merge
that passed that margin test where it was found (our own full merge, or the peer's, which publishes
only validated merges), and it is re-validated on the maps as they are now. What that trusts is the
provenance, so peer hints arrive only over swarm-key-authenticated transfers (docs/sharing.md).
A hint is also refused when ICP moved it far (HINT_MAX_SHIFT_M, HINT_MAX_TURN_DEG): then it was not
the transform it claimed to be, and the search decides. And when two hints of one map propose
distinct transforms that both validate, none is taken (try_hints): the full search decides.
A lone wrong hint can still validate (the mirror fit of a near-symmetric building does); the daemon
therefore sends a merged map through the full search again once the maps grew, its hints competing
there as hypotheses (merge_all contest, coopd/daemon/merger.py).

A vouched hint is a peer's edge between two other maps found on exactly the map versions we hold
(the edge names both versions): the peer already ran refinement and validation on those very maps,
so running them again here would redo its work. Only the link to the peer's map is refined and
validated here; the vouched edge is checked by agreement alone (check_vouched), and refined like
any hint when that check fails. In a swarm where one drone searches every pair, this drops the
others' merge work per map from a refinement to a check (scripts/bench swarm).
"""

from dataclasses import dataclass, replace

import numpy as np

from ..geometry import check_rigid, invert, rotation_angle_deg
from .pair import MergeResult, PreparedMap, as_given, distinct, judge
from .params import MergeParams

MAX_HINTS = 4
"""Hints tried per input map at most (each costs an ICP and a validation)."""
HINT_MAX_SHIFT_M = 1.0
HINT_MAX_TURN_DEG = 5.0
"""ICP may move an accepted hint at most this far (map drift between merges is centimetres)."""


@dataclass(frozen=True)
class Hint:
    """A candidate transform carrying an input map's frame into the reference frame.

    via: index of another input map whose transform in this merge is prepended (transform then
    carries this map's frame into that map's frame); resolved only once that map merged."""

    transform: np.ndarray
    source: str = "own"
    via: int | None = None
    vouched: bool = False
    """A peer's edge from the via map, found on the map versions we hold (checked, not refined)."""

    def __post_init__(self):
        object.__setattr__(self, "transform", check_rigid(self.transform))


def resolve(hint: Hint, merged: dict[int, np.ndarray]) -> np.ndarray | None:
    """The hint's transform into the reference frame, or None while its `via` map is not merged."""
    if hint.via is None:
        return hint.transform
    base = merged.get(hint.via)
    return None if base is None else base @ hint.transform


def validate_hint(a: PreparedMap, b: PreparedMap, t: np.ndarray, params: MergeParams) -> MergeResult:
    """judge(t), accepted only if ICP did not move t far either (else the hint was not what it claimed);
    also what re-anchors the FC's frame after a reboot (coopd.mapping.reanchor)."""
    r = judge(a, b, t, params)
    moved = (float(np.linalg.norm(r.transform[:3, 3] - t[:3, 3])),
             rotation_angle_deg(t[:3, :3].T @ r.transform[:3, :3]))
    ok = r.accepted and moved[0] <= HINT_MAX_SHIFT_M and moved[1] <= HINT_MAX_TURN_DEG
    return r if ok else replace(r, accepted=False, reason=r.reason if not r.accepted else "moved far by ICP")


def check_vouched(via: PreparedMap, b: PreparedMap, hint: Hint, base: np.ndarray,
                  params: MergeParams) -> MergeResult | None:
    """A vouched hint accepted without refinement when its edge passes validation's thresholds on the
    two maps it joins (b onto the via map, min_inliers aside: no ICP ran); its transform into the
    reference frame is base (the via map's) @ the edge. None: refine and validate it as any hint."""
    r = as_given(via, b, hint.transform, params, method=f"hint:{hint.source}")
    return replace(r, transform=base @ hint.transform) if r.accepted else None


def try_hints(a: PreparedMap, b: PreparedMap, candidates: list[tuple[np.ndarray, str]],
              params: MergeParams) -> tuple[MergeResult | None, int, list[int]]:
    """(first hint that validates, as a result with method "hint:<source>", or None; hints refused;
    positions of the refused ones that a larger global map cannot save: they disagree with it (score)
    or ICP moved them far, as opposed to overlapping it too little (few inliers or agreeing cells),
    so retrying them after a fuse would only cost CPU).

    The hints' own ambiguity check: when a later hint proposes a distinct transform (pair.distinct)
    that validates too, the maps fit two ways and the hints cannot tell which: all are refused and the
    full search, with its runner-up margin, decides. Hints normally agree, so this costs nothing."""
    cands = candidates[:MAX_HINTS]
    refused, final = 0, []
    for k, (t, source) in enumerate(cands):
        r = validate_hint(a, b, t, params)
        if r.accepted:
            for u in [u for u, _ in cands[k + 1:] if distinct(u, r.transform)]:
                refused += 1  # a rival hint: validated for the check only, never taken
                if validate_hint(a, b, u, params).accepted:
                    return None, refused + 1, final
            return replace(r, method=f"hint:{source}"), refused, final
        refused += 1
        if r.reason.startswith(("score", "moved far")):  # it disagrees with the map
            final.append(k)
    return None, refused, final


def hints_for(own_vid: int, vids: list[int], own: dict[int, np.ndarray], peer_results,
              held: dict[int, int] | None = None) -> list[list[Hint]]:
    """Hints per input map (vehicle ids `vids`, in merge order) from our own last accepted transforms
    (`own`: vehicle id -> transform into our frame) and peers' results (objects with vehicle_id and
    edges of a, b, transform carrying b's frame into a's, as wire.MergeResultMessage). held: the map
    version we hold per vehicle id (ours included); a hint whose edge names exactly those versions of
    both its maps is vouched, direct or chained: the peer refined and validated it on the very maps
    we hold.

    A peer vouches only for merges into its own frame (edges with a == its vehicle id). Its edge
    a->b gives b a hint directly when a is us, and the inverse to a when b is us; otherwise the
    hint leans on the other map's transform of this very merge (Hint.via), e.g. drone C with T_CA
    and A's T_AB tries T_CA @ T_AB for B. Own hints come first, then direct, then chained ones."""
    index = {v: i for i, v in enumerate(vids)}
    out: list[list[Hint]] = [[] for _ in vids]
    for v, i in index.items():
        if v in own:
            out[i].append(Hint(own[v], "own"))
    chained: list[tuple[int, Hint]] = []
    for msg in peer_results:
        if msg.vehicle_id == own_vid:
            continue
        for e in msg.edges:
            if e.a != msg.vehicle_id or e.a == e.b:
                continue
            t = np.asarray(e.transform, dtype=np.float64)
            vouched = held is not None and held.get(e.a) == e.version_a and held.get(e.b) == e.version_b
            for target, other, rel in ((e.b, e.a, t), (e.a, e.b, None)):
                if target not in index or other == target:
                    continue
                rel = rel if rel is not None else invert(t)
                if other == own_vid:
                    out[index[target]].append(Hint(rel, "peer", vouched=vouched))
                elif other in index:
                    chained.append((index[target], Hint(rel, "peer", via=index[other], vouched=vouched)))
    for i, h in chained:
        out[i].append(h)
    return [h[:MAX_HINTS] for h in out]

"""scripts/bench merge_replay: recorded flights replayed through the daemon's merging thread (Merger)
under the merging rules before rechecks ("old": conflict_weight 3, no rechecks; every search
hypothesis refined, as today), with rechecks but every accepted fit fused at once ("rechecks") and
today's defaults ("new": a newly found fit is provisional, held out of the global map until confirmed).

--record DIR flies one recording: firmware_sim.swarm.Swarm with N real coopd daemons; every few
seconds every daemon's local map is dumped through its control socket (DIR/<tag>_d<i>.cmap, tags
s000, s001, ..., then "final" after merge_until_converged) and DIR/log.json gets a record per
snapshot: truth["a<-b"] (4x4, carries drone b's map frame into drone a's, from Swarm.map_to_world),
the offsets the daemons merged and their merge counters.
--replay DIR ...: for every drone a of a recording and every rule set, a Merger (vehicle a, not
distributed, merge_all) is fed snapshot after snapshot its local map and the other drones' maps
(a drone's latest dump; versions grow with the snapshots), one merge_once per snapshot, and once more
on the last one while a merge is provisional (the daemon merges again to confirm). After each, every
accepted offset is judged against truth["a<-b"]: right within --tol-m and --tol-deg.
Per recording and rule set, and summed per rule set ("all"): ordered pairs, right / wrong / not
merged at the end, snapshot-states (recorded snapshots only) with a right or a wrong transform in the
global map (right_states, wrong_states) and with a provisional one held out of it (held_states),
merge CPU (Merger.cpu_s), full registrations, rechecks.
Prints a table and writes out/bench/merge_replay.json.
Usage: scripts/bench merge_replay --replay /tmp/repro/r1 /tmp/repro/sh2 [--rules old,rechecks,new]
       scripts/bench merge_replay --record DIR [--world small_house] [--seed 0] [--drones 2]
"""

import argparse
import json
import logging
import re
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path[:0] = [str(ROOT)]

from coopd.daemon.budget import MemoryBudget  # noqa: E402
from coopd.daemon.config import MergingConfig, SharingConfig  # noqa: E402
from coopd.daemon.merge_state import MergerSettings, MergeSources  # noqa: E402
from coopd.daemon.merger import Merger  # noqa: E402
from coopd.geometry import invert  # noqa: E402
from coopd.io.cmap import read_cmap_bytes  # noqa: E402
from coopd.merging import merge_all  # noqa: E402
from coopd.merging.params import coopd_params  # noqa: E402
from coopd.sharing.wire import DecodeLimits, decode_map  # noqa: E402
from firmware_sim.accuracy import offset_error  # noqa: E402

RULES = {
    "old": (coopd_params().with_(conflict_weight=3.0), None, False),
    "rechecks": (coopd_params(), MergingConfig().recheck_growth, False),
    "new": (coopd_params(), MergingConfig().recheck_growth, MergingConfig().confirm_before_fusing),
}
"""Rule set -> (merging params, MergerSettings recheck_growth, confirm_before_fusing); recheck_growth None:
no rechecks at all. "rechecks" are session 3's rules, "new" today's defaults."""
LIMITS = DecodeLimits(SharingConfig().max_map_cells, SharingConfig().max_map_bytes)
"""The daemon's default limits on received maps."""
BUDGET_BYTES = 16 << 30
"""The replay's Merger never defers a merge for memory."""
STATE_CHARS = {"right": "R", "wrong": "W", "none": ".", "right held": "r", "wrong held": "w"}
"""A pair's state after a merge; held: accepted but provisional, out of the global map."""


# ------------------------------------------------------------------------------------ record
def record(out: Path, args) -> None:
    """Fly one recording into out (log.json and the snapshots' local maps); see the module docstring."""
    from firmware_sim.swarm import Swarm, SwarmSettings

    out.mkdir(parents=True, exist_ok=True)
    settings = SwarmSettings(drones=args.drones, world=args.world, seed=args.seed, speed=args.speed,
                             mavlink_base=args.mavlink_base, sharing_port=args.sharing_port,
                             subnet=args.subnet, fc_subnet=args.fc_subnet)
    swarm = Swarm(settings, say=print)
    log: list[dict] = []
    try:
        swarm.start()
        swarm.fly()
        t0, k = time.monotonic(), 0
        while not swarm.landed() and time.monotonic() - t0 < args.flight_limit_s:
            time.sleep(args.every_s)
            log.append(snapshot(swarm, out, f"s{k:03d}"))
            write_log(out, log)
            k += 1
        swarm.merge_until_converged(limit_s=args.merge_limit_s)
        log.append(snapshot(swarm, out, "final"))
        write_log(out, log)
        statuses = swarm.statuses()
        for i in range(args.drones):
            print(i + 1, json.dumps(swarm.offset_errors(i, statuses)))
    finally:
        swarm.stop(keep_files=True)
        print("daemons' files in", swarm.workdir)


def snapshot(swarm, out: Path, tag: str) -> dict:
    """Dump every daemon's local map as <tag>_d<i>.cmap; the record: truth, merged offsets, counters."""
    statuses = swarm.statuses()
    rec = {"tag": tag, "t": time.time(), "merged": {}, "merges": {}, "truth": {}}
    for i, daemon in enumerate(swarm.daemons):
        try:
            _, blob = daemon.request("dump-map", {"map": "local"}, timeout_s=30, max_blob_bytes=1 << 28)
            (out / f"{tag}_d{i + 1}.cmap").write_bytes(blob)
        except Exception as e:  # a daemon busy or gone: the replay keeps its previous map
            print(f"{tag}: dump of drone {i + 1} failed: {e}")
        rec["merged"][i + 1] = {k: v["transform"] for k, v in swarm.merged_vehicles(statuses[i]).items()}
        rec["merges"][i + 1] = (statuses[i] or {}).get("merges")
    frames = [swarm.map_to_world(i, statuses[i]) for i in range(len(swarm.daemons))]
    for i, a in enumerate(frames):
        for j, b in enumerate(frames):
            if i != j:
                rec["truth"][f"{i + 1}<-{j + 1}"] = (invert(a) @ b).tolist()
    return rec


def write_log(out: Path, log: list[dict]) -> None:
    (out / "log.json").write_text(json.dumps(log))


# ------------------------------------------------------------------------------------ replay
def load_recording(path: Path) -> dict:
    """A recording's snapshots (tag, truth per (a, b)) and its drones' ids."""
    log = json.loads((path / "log.json").read_text())
    snaps = []
    for rec in log:
        truth = {}
        for key, t in rec["truth"].items():
            a, b = map(int, key.split("<-"))
            truth[(a, b)] = np.asarray(t, dtype=np.float64)
        snaps.append({"tag": rec["tag"], "truth": truth})
    found = {int(m.group(1)) for f in path.glob("*.cmap") if (m := re.search(r"_d(\d+)\.cmap$", f.name))}
    drones = sorted(found | {v for s in snaps for pair in s["truth"] for v in pair})
    return {"name": path.name, "path": path, "snapshots": snaps, "drones": drones}


class Feed:
    """What the Merger of one drone reads: its local map and the other drones' maps, each the drone's
    latest dump up to the current snapshot (a failed dump keeps the previous map and version)."""

    def __init__(self, recording: dict, vehicle_id: int):
        self.recording, self.vehicle_id = recording, vehicle_id
        self.maps: dict[int, tuple[int, bytes]] = {}
        self.grid = None

    def advance(self, k: int) -> bool:
        """Move to snapshot k; False while there is no local map yet."""
        tag = self.recording["snapshots"][k]["tag"]
        for vid in self.recording["drones"]:
            path = self.recording["path"] / f"{tag}_d{vid}.cmap"
            if path.exists():
                self.maps[vid] = (k + 1, read_cmap_bytes(path, LIMITS))
                if vid == self.vehicle_id:
                    self.grid = decode_map(self.maps[vid][1], LIMITS)[0]
        return self.grid is not None

    def local(self):
        return self.grid.copy(), self.maps[self.vehicle_id][0]

    def received(self) -> list:
        return [SimpleNamespace(vehicle_id=vid, version=version, data=data)
                for vid, (version, data) in sorted(self.maps.items()) if vid != self.vehicle_id]


def judge(offset: dict | None, truth: np.ndarray, tol_m: float, tol_deg: float) -> tuple[str, list | None]:
    """A Merger offset entry against the truth: ("right" | "wrong" | "none", with " held" when
    provisional; [error m, error deg])."""
    if not offset or not offset["accepted"]:
        return "none", None
    err = offset_error(np.reshape(offset["transform"], (4, 4)), truth)
    right = err[0] <= tol_m and err[1] <= tol_deg
    return ("right" if right else "wrong") + (" held" if offset.get("provisional") else ""), \
        [round(v, 3) for v in err]


def replay_drone(recording: dict, vehicle_id: int, rules: str, tol_m: float, tol_deg: float) -> dict:
    """One drone's Merger over every snapshot: per other drone its state history and final error."""
    params, recheck_growth, confirm = RULES[rules]
    feed = Feed(recording, vehicle_id)
    settings = MergerSettings(period_s=3600, params=params, limits=LIMITS, distributed=False,
                              recheck_growth=recheck_growth, confirm_before_fusing=confirm)
    merger = Merger(vehicle_id, settings, MergeSources(feed.local, feed.received),
                    MemoryBudget(BUDGET_BYTES, baseline_bytes=0), merge_fn=merge_all)
    others = [v for v in recording["drones"] if v != vehicle_id]
    pairs = {b: {"history": "", "recorded": 0, "final": "none", "error": None} for b in others}
    """recorded: how many history states belong to recorded snapshots (not the merge to confirm)."""
    snaps = recording["snapshots"]
    for k, snap in enumerate([*snaps, snaps[-1]]):  # the last twice: the daemon merges again to confirm
        if not feed.advance(min(k, len(snaps) - 1)):
            continue
        if k == len(snaps) and not merger.status()["provisional"]:
            break
        merger.merge_once(snap["tag"])
        for b in others:
            truth = snap["truth"].get((vehicle_id, b))
            if truth is None:
                continue
            state, err = judge(merger.offsets.get(b), truth, tol_m, tol_deg)
            pairs[b]["history"] += STATE_CHARS[state]
            pairs[b]["recorded"] += k < len(snaps)
            pairs[b]["final"], pairs[b]["error"] = state, err
    return {"pairs": pairs, "cpu_s": merger.cpu_s, "counters": dict(merger.counters)}


def replay(recording: dict, rules: str, tol_m: float, tol_deg: float) -> dict:
    """Every drone's Merger of one recording under one rule set, summed up."""
    row = {"recording": recording["name"], "rules": rules, "drones": len(recording["drones"]),
           "snapshots": len(recording["snapshots"]), "pairs": 0, "right": 0, "wrong": 0,
           "not_merged": 0, "right_states": 0, "wrong_states": 0, "held_states": 0, "cpu_s": 0.0,
           "full_registrations": 0, "rechecks": 0, "detail": {}}
    for a in recording["drones"]:
        drone = replay_drone(recording, a, rules, tol_m, tol_deg)
        row["cpu_s"] += drone["cpu_s"]
        row["full_registrations"] += drone["counters"]["full_registrations"]
        row["rechecks"] += drone["counters"]["rechecks"]
        for b, pair in drone["pairs"].items():
            row["pairs"] += 1
            row["right" if pair["final"] == "right" else "wrong" if pair["final"] == "wrong"
                else "not_merged"] += 1
            states = pair["history"][:pair["recorded"]]
            row["right_states"] += states.count(STATE_CHARS["right"])
            row["wrong_states"] += states.count(STATE_CHARS["wrong"])
            row["held_states"] += sum(states.count(STATE_CHARS[s]) for s in ("right held", "wrong held"))
            row["detail"][f"{a}<-{b}"] = pair
    row["cpu_s"] = round(row["cpu_s"], 2)
    return row


COLUMNS = ("recording", "rules", "snapshots", "pairs", "right", "wrong", "not_merged", "right_states",
           "wrong_states", "held_states", "cpu_s", "full_registrations", "rechecks")
SUMMED = COLUMNS[2:]


def totals(rows: list[dict]) -> list[dict]:
    """One row per rule set ("all" recordings): every count summed, in the order the rules came."""
    out: dict[str, dict] = {}
    for r in rows:
        t = out.setdefault(r["rules"], {"recording": "all", "rules": r["rules"], **dict.fromkeys(SUMMED, 0)})
        for c in SUMMED:
            t[c] += r[c]
    for t in out.values():
        t["cpu_s"] = round(t["cpu_s"], 2)
    return list(out.values())


def table(rows: list[dict]) -> str:
    """The rows as a text table, one line per recording and rule set and the totals per rule set,
    then each pair's history."""
    shown = rows + totals(rows)
    widths = [max(len(c), *(len(str(r[c])) for r in shown)) for c in COLUMNS]
    lines = ["  ".join(c.rjust(w) for c, w in zip(COLUMNS, widths, strict=True))]
    lines += ["  ".join(str(r[c]).rjust(w) for c, w in zip(COLUMNS, widths, strict=True)) for r in shown]
    lines.append("pair histories per snapshot (R right, W wrong, . not merged; r, w: provisional, held out "
                 "of the global map):")
    for r in rows:
        lines.append(f"  {r['recording']} {r['rules']}: "
                     + ", ".join(f"{pair} {p['history']}" for pair, p in r["detail"].items()))
    return "\n".join(lines)


# -------------------------------------------------------------------------------------- main
def parse(argv=None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    mode = ap.add_mutually_exclusive_group(required=True)
    mode.add_argument("--record", type=Path, metavar="DIR", help="fly one recording into DIR")
    mode.add_argument("--replay", type=Path, nargs="+", metavar="DIR", help="replay these recordings")
    ap.add_argument("--rules", default="old,rechecks,new", help=f"rule sets to replay, of {','.join(RULES)}")
    ap.add_argument("--tol-m", type=float, default=0.3)
    ap.add_argument("--tol-deg", type=float, default=3.0)
    ap.add_argument("--out", type=Path, default=ROOT / "out" / "bench" / "merge_replay.json")
    ap.add_argument("--world", default="small_house")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--drones", type=int, default=2)
    ap.add_argument("--speed", type=float, default=2.0, help="simulated seconds per wall second")
    ap.add_argument("--every-s", type=float, default=2.0, help="wall seconds between snapshots")
    ap.add_argument("--flight-limit-s", type=float, default=300.0)
    ap.add_argument("--merge-limit-s", type=float, default=150.0)
    ap.add_argument("--mavlink-base", type=int, default=23000)
    ap.add_argument("--sharing-port", type=int, default=23010)
    ap.add_argument("--subnet", default="10.214.77", help="swarm network /24 (netns mode)")
    ap.add_argument("--fc-subnet", default="10.215.77", help="FC cables' /24 (netns mode)")
    args = ap.parse_args(argv)
    unknown = set(args.rules.split(",")) - set(RULES)
    if unknown:
        ap.error(f"unknown rule sets {sorted(unknown)}; known: {', '.join(RULES)}")
    return args


def main(argv=None) -> list[dict] | None:
    args = parse(argv)
    if args.record is not None:
        record(args.record, args)
        return None
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    rows = []
    for path in args.replay:
        recording = load_recording(path)
        for rules in args.rules.split(","):
            rows.append(replay(recording, rules, args.tol_m, args.tol_deg))
    print(table(rows))
    report = {"tol_m": args.tol_m, "tol_deg": args.tol_deg,
              "rules": {k: {"conflict_weight": p.conflict_weight, "recheck_growth": g,
                            "confirm_before_fusing": c}
                        for k, (p, g, c) in RULES.items()},
              "rows": rows, "totals": totals(rows)}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(report, indent=1))
    print("written", args.out)
    return rows


if __name__ == "__main__":
    main()

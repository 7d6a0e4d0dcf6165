"""scripts/bench swarm: time for N coopd daemons to share their maps and to each hold the full global map.

The thesis experiment (§10.4): the maps are already built, then shared and merged. Each of N real
`coopd` processes on loopback resumes, as after a restart, from a checkpoint holding one drone's
real flight map of one world (firmware_sim/simset.py: every drone of one seeded flight, its own
start pose and route, mapped with its drifting odometry; flown once, then cached in out/simset/).
MAVLink points at a silent udpin port and the camera at a missing socket: the daemons are grounded.
Each daemon is frozen (SIGSTOP) once it runs, and all resume together at t = 0, so no daemon
shares or merges while the others still start. Until every daemon:
  t_share   holds every other's map (status peers[].map_version),
  t_global  has N-1 accepted merge offsets (status merges.offsets), each checked against the
            flight's truth (translation error < --tol-m, yaw/rotation < --tol-deg; else "wrong").
The bench asks each daemon for the peers and merges of its status twice a second, and stops asking
one once it holds every map and the global map (the whole status is asked once more at the end): a
status request costs the daemon CPU that its merges need, measured at the end as
status_request_cpu_ms (whole and as polled).
Also per daemon: merges done/failed/deferred, merge CPU (as the daemon reports it: its merging
thread and the search threads it starts; the merging thread alone from /proc), process CPU, peak
RSS, and per merged map its mean displacement (its occupied cells placed by the offset vs by the
truth; the table's "shift m" is the median/max over all merges). When the daemon's config has
`[merging] distributed`, every size runs both ways (the peer comparison).
Prints a table and writes out/bench/swarm.json.
With --transport mtp,zenoh every size also runs with the maps shared over Zenoh (peers on loopback,
multicast scouting off, each connecting to drone 1 and finding the others by gossip).
--camera-rate flies the maps with every emulated camera at that rate (fewer frames: a flight of many
drones fits a small machine; each map a little sparser), stated in the output and the JSON.
Usage: scripts/bench swarm [--drones 2,4,6,8,10] [--transport mtp,zenoh] [--modes distributed]
                           [--world small_house] [--seed 1] [--vehicles 10] [--camera-rate HZ]
                           [--timeout 300]
"""

import argparse
import ctypes
import dataclasses
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path[:0] = [str(ROOT)]

from coopd.cli.key_commands import key_file_text  # noqa: E402
from coopd.daemon.checkpoint import CheckpointStore  # noqa: E402
from coopd.daemon.config import MergingConfig  # noqa: E402
from coopd.daemon.control import ControlError, request  # noqa: E402
from coopd.daemon.merger import in_global_map  # noqa: E402
from coopd.daemon.service import save_map_frame  # noqa: E402
from coopd.geometry import rotation_angle_deg  # noqa: E402
from coopd.grid.cells import OCCUPIED_THRESHOLD  # noqa: E402
from coopd.sharing.wire import MapMeta  # noqa: E402
from firmware_sim import simset  # noqa: E402
from firmware_sim.swarm import render_config  # noqa: E402

THESIS = {"drones": 10, "t_share_s": 6.0, "t_merge_s": 340.0, "t_total_s": 350.0,
          "machine": "thesis §10.4, i7 (C++)"}
GOAL_TOTAL_S = 60.0
"""Issue 7: 10 drones, everything shared and merged everywhere, on this 2-core machine."""
SHARING_BASE, MAVLINK_BASE, ZENOH_BASE = 18000, 18500, 18200
"""Ports of this bench: sharing 18001.., silent MAVLink udpin 18501.., Zenoh 18201.. (vehicle id added)."""
HOST_BASE = 10
"""Vehicle i listens and sends from 127.0.0.(HOST_BASE + i): like drones, each its own address (a map
server admits at most max_connections_per_address = 4 connections from one address; on one shared
127.0.0.1, a daemon with more than 5 peers gets the others' maps only as idle connections time out)."""


def host(vid: int, shared_address: bool = False) -> str:
    """The loopback address of vehicle vid."""
    return "127.0.0.1" if shared_address else f"127.0.0.{HOST_BASE + vid}"
MERGE_COUNTERS = ("done", "failed", "deferred", "nothing_to_merge", "unchanged")
POLL_S = 0.5
POLLED_SECTIONS = ["peers", "merges"]
"""What the bench reads of a status while it waits (the whole status is asked for at the end)."""
"""Status polls of every daemon: each costs the daemon a little CPU, taken from merging."""
STATUS_TIMEOUT_S = 10.0


# ------------------------------------------------------------------------------- pure checks
def offset_errors(transform: list[float] | np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    """(translation error m, rotation error deg) of a reported offset (16 numbers, row-major) vs truth."""
    t = np.asarray(transform, dtype=np.float64).reshape(4, 4)
    rot = rotation_angle_deg(t[:3, :3].T @ truth[:3, :3])
    return float(np.linalg.norm(t[:3, 3] - truth[:3, 3])), float(rot)


def displacement_m(transform: list[float] | np.ndarray, truth: np.ndarray, points: np.ndarray) -> float:
    """Mean distance between a map's points (its frame, metres) placed by a reported offset and by
    the truth: the registration error over the whole map, not only at its origin."""
    t = np.asarray(transform, dtype=np.float64).reshape(4, 4)
    moved = points @ t[:3, :3].T + t[:3, 3]
    true = points @ truth[:3, :3].T + truth[:3, 3]
    return float(np.linalg.norm(moved - true, axis=1).mean()) if len(points) else 0.0


def occupied_points(grid, max_points: int = 20_000) -> np.ndarray:
    """Centres (metres) of a grid's occupied cells, thinned evenly to about max_points."""
    keys = np.argwhere(grid.cells >= OCCUPIED_THRESHOLD)
    keys = keys[:: max(1, len(keys) // max_points)]
    return (keys + grid.offset) * grid.resolution


def judge_offsets(offsets: dict, truths: dict[int, np.ndarray], tol_m: float, tol_deg: float,
                  points: dict[int, np.ndarray] | None = None) -> dict:
    """One daemon's status merges.offsets against the truth per peer id: accepted, correct, wrong ids
    and the errors of the accepted ones (translation m, rotation deg, and with points, the map's
    mean displacement m). A merge is correct within tol_m and tol_deg."""
    out = {"accepted": [], "correct": [], "wrong": [], "errors": {}, "refused": {}}
    for key, o in sorted(offsets.items(), key=lambda kv: int(kv[0])):
        vid = int(key)
        if vid not in truths:
            continue
        if not in_global_map(o):
            why = "provisional, held out of the global map" if o.get("accepted") else o.get("reason")
            out["refused"][vid] = f"{why} (score {o.get('score')})"
            continue
        te, re = offset_errors(o["transform"], truths[vid])
        out["accepted"].append(vid)
        out["errors"][vid] = [round(te, 3), round(re, 2)]
        if points is not None and vid in points:
            out["errors"][vid].append(round(displacement_m(o["transform"], truths[vid], points[vid]), 3))
        out["correct" if te < tol_m and re < tol_deg else "wrong"].append(vid)
    return out


def holds_all_maps(status: dict, ids: list[int]) -> bool:
    """True when this daemon's status shows a received map of every other vehicle in ids."""
    held = {p["vehicle_id"] for p in status.get("peers", []) if p.get("map_version") is not None}
    return set(ids) - {status["vehicle_id"]} <= held


def gave_up(earlier: dict, later: dict, ids: list[int]) -> bool:
    """True when a daemon holding every map, idle, merged nothing since `earlier` and skipped a merge
    of unchanged inputs (merges.unchanged): without new maps its global map will not change."""
    m0, m1 = earlier.get("merges", {}), later.get("merges", {})
    return (holds_all_maps(later, ids) and m1.get("state") == "idle" and m1.get("done") == m0.get("done")
            and m1.get("unchanged", 0) > m0.get("unchanged", 0) and m1.get("done", 0) >= 1)


def accepted_offsets(status: dict) -> set[int]:
    """Vehicle ids this daemon's last merge accepted into its global map (not provisional ones)."""
    return {int(k) for k, o in status.get("merges", {}).get("offsets", {}).items() if in_global_map(o)}


def holds_global(status: dict, ids: list[int]) -> bool:
    """True when this daemon's global map holds every other vehicle's map (N-1 accepted offsets)."""
    return set(ids) - {status["vehicle_id"]} <= accepted_offsets(status)


def still_waiting(ids: list[int], first_global: dict[int, float], last: dict[int, dict]) -> list[int]:
    """The daemons the bench still asks for their status: all but those that held the global map
    (first_global) and hold every map. Each status costs the daemon CPU (status_request_cpu_ms) that
    the swarm's merges need."""
    return [v for v in ids if not (v in first_global and holds_all_maps(last[v], ids))]


# ------------------------------------------------------------------------------------ the swarm
def cpu_s(stat_path: str) -> float | None:
    """CPU seconds (user + system) from a /proc stat file (/proc/PID/stat, /proc/PID/task/TID/stat)."""
    try:
        with open(stat_path, "rb") as f:
            stat = f.read().decode()
    except OSError:
        return None
    fields = stat[stat.rindex(")") + 2:].split()  # after "pid (comm) ": field 3 onwards
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def die_with_parent() -> None:
    """In a daemon's child process before exec: SIGKILL it when the bench dies, even by SIGKILL."""
    PR_SET_PDEATHSIG = 1
    ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGKILL)


class Swarm:
    """N coopd processes on loopback, each resumed from one flight map; stop() kills what is left."""

    def __init__(self, maps: list, merging: dict, workdir: Path, shared_address: bool = False,
                 transport: str = "mtp"):
        self.maps = maps
        self.transport = transport
        self.shared_address = shared_address
        self.ids = [i + 1 for i in range(len(maps))]
        self.workdir = workdir
        self.merging = merging
        self.procs: dict[int, subprocess.Popen] = {}
        self.logs = {}
        self.started: dict[int, dict] = {}
        """Each daemon's status when it first ran (its thread ids, for CPU from /proc while frozen)."""

    def sock(self, vid: int) -> str:
        return str(self.workdir / f"d{vid}" / "ctl.sock")

    def prepare(self) -> None:
        """Each daemon's state dir: its map as the local checkpoint (version 1), its map frame, its config."""
        key_file = self.workdir / "swarm.key"  # one key for the whole bench swarm (secure by default)
        key_file.write_text(key_file_text(os.urandom(32)))
        key_file.chmod(0o600)
        for vid, m in zip(self.ids, self.maps, strict=True):
            d = self.workdir / f"d{vid}"
            store = CheckpointStore(d / "state")
            if store.save("local", m.grid, MapMeta(vid, 1, time.time())) is None:
                raise RuntimeError(f"checkpoint of vehicle {vid} not written: {store.last_error}")
            save_map_frame(d / "state", vid, [0.0, 0.0, 0.0])
            config = {
                "vehicle": {"id": vid, "mavlink": f"udpin:127.0.0.1:{MAVLINK_BASE + vid}"},
                "camera": {"source": f"socket:{d / 'no-camera.sock'}"},
                "sharing": {"listen_host": host(vid, self.shared_address), "port": SHARING_BASE + vid,
                            "peers": [f"{host(o, self.shared_address)}:{SHARING_BASE + o}"
                                      for o in self.ids if o != vid],
                            "swarm_key_file": str(key_file), **self.zenoh_sharing(vid)},
                "merging": self.merging,
                "daemon": {"state_dir": str(d / "state"), "control_socket": self.sock(vid)},
            }
            (d / "coopd.toml").write_text(render_config({k: v for k, v in config.items() if v}))

    def zenoh_sharing(self, vid: int) -> dict:
        """The [sharing] keys of the Zenoh transport: each daemon listens on its own address and connects
        to drone 1's; the others are found by gossip."""
        if self.transport == "mtp":
            return {}
        first = f"tcp/{host(1, self.shared_address)}:{ZENOH_BASE + 1}"
        return {"transport": self.transport,
                "zenoh": {"swarm": "bench",
                          "listen": [f"tcp/{host(vid, self.shared_address)}:{ZENOH_BASE + vid}"],
                          "connect": [first] if vid != 1 else [], "multicast_scouting": False}}

    def start(self, timeout_s: float) -> float:
        """Start every daemon, freeze each once it runs; returns the seconds until all ran."""
        env = dict(os.environ, PYTHONPATH=str(ROOT), PYTHONUNBUFFERED="1")
        env.pop("NOTIFY_SOCKET", None)
        env.pop("WATCHDOG_USEC", None)
        t0 = time.monotonic()
        for vid in self.ids:
            d = self.workdir / f"d{vid}"
            self.logs[vid] = open(d / "coopd.log", "wb")
            self.procs[vid] = subprocess.Popen(
                [sys.executable, "-m", "coopd.daemon.main", "--config", str(d / "coopd.toml")],
                stdout=self.logs[vid], stderr=subprocess.STDOUT, env=env, cwd=ROOT,
                preexec_fn=die_with_parent)
        waiting = set(self.ids)
        while waiting:
            if time.monotonic() - t0 > timeout_s:
                raise RuntimeError(f"daemons {sorted(waiting)} not running after {timeout_s:.0f} s")
            for vid in sorted(waiting):
                if self.procs[vid].poll() is not None:
                    tail = (self.workdir / f"d{vid}" / "coopd.log").read_text()[-1500:]
                    raise RuntimeError(f"daemon {vid} exited ({self.procs[vid].returncode}):\n{tail}")
                st = self.status(vid)
                if st is not None and st.get("state") == "running":
                    os.kill(self.procs[vid].pid, signal.SIGSTOP)
                    self.started[vid] = st
                    waiting.discard(vid)
            time.sleep(POLL_S)
        return time.monotonic() - t0

    def resume(self) -> None:
        for vid in self.ids:
            os.kill(self.procs[vid].pid, signal.SIGCONT)

    def status(self, vid: int, sections: list[str] | None = None) -> dict | None:
        """Daemon vid's status (only `sections` of it, when given), or None if it does not answer."""
        args = None if sections is None else {"sections": sections}
        try:
            return request(self.sock(vid), "status", args, timeout_s=STATUS_TIMEOUT_S)[0]
        except (ControlError, OSError):
            return None

    def cpu(self, vid: int) -> dict:
        """CPU seconds so far of daemon vid: the whole process and its merging thread."""
        pid = self.procs[vid].pid
        threads = self.started[vid].get("threads", [])
        tid = next((t["tid"] for t in threads if t.get("thread") == "coopd-merging"), None)
        merging = None if tid is None else cpu_s(f"/proc/{pid}/task/{tid}/stat")
        return {"process": cpu_s(f"/proc/{pid}/stat"), "merging_thread": merging}

    def stop(self) -> None:
        """SIGCONT + SIGTERM every daemon, SIGKILL those still there after 10 s."""
        for p in self.procs.values():
            if p.poll() is None:
                for sig in (signal.SIGCONT, signal.SIGTERM):
                    try:
                        p.send_signal(sig)
                    except ProcessLookupError:
                        pass
        deadline = time.monotonic() + 10
        for p in self.procs.values():
            try:
                p.wait(max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait(5)
        for f in self.logs.values():
            f.close()


# ------------------------------------------------------------------------------------ one run
def run_size(maps: list, merging: dict, args, label: str, transport: str = "mtp") -> dict:
    """Start N daemons, measure sharing and merging until converged or args.timeout; the row."""
    n = len(maps)
    truths = {a.vehicle + 1: {b.vehicle + 1: simset.truth_b_to_a(a, b) for b in maps if b is not a}
              for a in maps}
    workdir = Path(tempfile.mkdtemp(prefix="bsw", dir="/tmp"))
    swarm = Swarm(maps, merging, workdir, args.shared_address, transport)
    row = {"drones": n, "mode": label, "transport": transport, "merging_config": merging,
           "shared_address": args.shared_address}
    try:
        swarm.prepare()
        row["startup_s"] = round(swarm.start(args.start_timeout), 1)
        cpu0 = {vid: swarm.cpu(vid) for vid in swarm.ids}
        swarm.resume()
        t0 = time.monotonic()
        row["load_avg_1min_at_start"] = round(os.getloadavg()[0], 2)  # the machine is shared: noise
        t_share = t_global = None
        first_global: dict[int, float] = {}
        last: dict[int, dict] = {}
        since_merge: dict[int, dict] = {}
        """Each daemon's first status after its last merge done (did it skip unchanged ones since?)."""
        polls = 0
        while time.monotonic() - t0 < args.timeout:
            waiting = still_waiting(swarm.ids, first_global, last)
            for vid in waiting:
                st = swarm.status(vid, POLLED_SECTIONS)
                polls += 1
                if st is not None:
                    last[vid] = st
                    if since_merge.get(vid, {}).get("merges", {}).get("done") != st["merges"]["done"]:
                        since_merge[vid] = st
            now = time.monotonic() - t0
            if len(last) == n:
                if t_share is None and all(holds_all_maps(s, swarm.ids) for s in last.values()):
                    t_share = now
                for vid, s in last.items():
                    if vid not in first_global and holds_global(s, swarm.ids):
                        first_global[vid] = now
                if t_global is None and len(first_global) == n:
                    t_global = now
            if t_share is not None and t_global is not None:
                break
            if len(last) == n and all(gave_up(since_merge[v], last[v], swarm.ids) for v in waiting):
                row["gave_up_at_s"] = round(now, 2)  # every daemon short of the global map settled
                break
            time.sleep(POLL_S)
        row["status_polls"] = polls
        last |= {vid: st for vid in swarm.ids if (st := swarm.status(vid)) is not None}
        cpu1 = {vid: swarm.cpu(vid) for vid in swarm.ids}
        row["load_avg_1min_at_end"] = round(os.getloadavg()[0], 2)
        points = {m.vehicle + 1: occupied_points(m.grid) for m in maps}
        row |= summarise(swarm, last, cpu0, cpu1, truths, args, t_share, t_global, first_global, points)
        if t_global is not None and args.linger > 0:
            row["after_global"] = linger(swarm, last, cpu1, args.linger)
        row["status_request_cpu_ms"] = status_cost(swarm)
    finally:
        swarm.stop()
        if args.keep:
            row["workdir"] = str(workdir)
        else:
            shutil.rmtree(workdir, ignore_errors=True)
    return row


def linger(swarm: Swarm, at_global: dict, cpu1: dict, seconds: float) -> dict:
    """What the daemons still do for `seconds` once every one holds the global map (all of it waste
    while no map changes): merges done, merges running at the end, merging-thread CPU."""
    time.sleep(seconds)
    end = {vid: swarm.status(vid) for vid in swarm.ids}
    cpu2 = {vid: swarm.cpu(vid) for vid in swarm.ids}
    live = [v for v in swarm.ids if end[v] is not None and v in at_global]
    return {
        "seconds": seconds,
        "merges_done": sum(end[v]["merges"]["done"] - at_global[v]["merges"]["done"] for v in live),
        "merging_at_end": sum(end[v]["merges"]["state"] == "merging" for v in live),
        "unchanged_skipped": sum(end[v]["merges"].get("unchanged", 0) for v in live),
        "merging_thread_cpu_s": round(sum(_delta(cpu2[v]["merging_thread"], cpu1[v]["merging_thread"]) or 0.0
                                          for v in swarm.ids), 2),
    }


STATUS_COST_REQUESTS = 40


def status_cost(swarm: Swarm, vids=(2, 3)) -> dict[str, float | None]:
    """CPU milliseconds one `status` request costs a daemon, whole and as the bench polls it (median of
    two daemons): its process CPU over STATUS_COST_REQUESTS requests in a row, less its CPU over as
    long a quiet spell before."""
    costs: dict[str, list[float]] = {"whole": [], "polled": []}
    for vid in vids:
        if vid not in swarm.ids or swarm.status(vid) is None:
            continue
        path = f"/proc/{swarm.procs[vid].pid}/stat"
        for kind, sections in (("whole", None), ("polled", POLLED_SECTIONS)):
            c0, t0 = cpu_s(path), time.monotonic()
            time.sleep(1.0)
            quiet = (cpu_s(path) - c0) / (time.monotonic() - t0)
            c0, t0 = cpu_s(path), time.monotonic()
            for _ in range(STATUS_COST_REQUESTS):
                swarm.status(vid, sections)
            costs[kind].append((cpu_s(path) - c0 - quiet * (time.monotonic() - t0)) / STATUS_COST_REQUESTS)
    return {k: round(1e3 * float(np.median(v)), 2) if v else None for k, v in costs.items()}


def sharing_failures(sharing: dict) -> dict[str, int]:
    """A daemon's refused or dropped transfers by cause, over every peer and unidentified senders (e.g.
    'busy': a Zenoh publication dropped because the receive queue was full)."""
    out: dict[str, int] = {}
    per_source = [p.get("failures", {}) for p in sharing.get("peers", [])]
    per_source += list(sharing.get("unidentified_failures", {}).values())
    for failures in per_source:
        for cause, n in failures.items():
            out[cause] = out.get(cause, 0) + n
    return out


def bytes_sent(sharing: dict) -> int:
    """Bytes a daemon handed over for sharing: MTP transfers to every peer (one per peer), and Zenoh
    publications and query replies (one per publication: Zenoh then sends it on every link to a
    subscriber, so on the wire a peer-to-peer swarm carries up to one copy per peer)."""
    return (sum(p.get("bytes_sent", 0) for p in sharing.get("peers", []))
            + (sharing.get("zenoh") or {}).get("bytes_out", 0))


def summarise(swarm: Swarm, last: dict, cpu0: dict, cpu1: dict, truths: dict, args, t_share, t_global,
              first_global, points: dict[int, np.ndarray] | None = None) -> dict:
    """The figures of one run from the daemons' last statuses (points: each vehicle's occupied cell
    centres, for the mean displacement of its map in every global map)."""
    daemons = []
    for vid in swarm.ids:
        st = last.get(vid)
        if st is None:
            daemons.append({"vehicle": vid, "status": "never answered"})
            continue
        merges = st["merges"]
        cpu = cpu1[vid]
        j = judge_offsets(merges.get("offsets", {}), truths[vid], args.tol_m, args.tol_deg, points)
        held = sorted(p["vehicle_id"] for p in st["peers"] if p.get("map_version") is not None)
        daemons.append({
            "vehicle": vid,
            "held_maps": held,
            "missing_maps": sorted(set(swarm.ids) - set(held) - {vid}),
            "sharing_failures": sharing_failures(st.get("sharing") or {}),
            "merges": {k: merges.get(k) for k in MERGE_COUNTERS},
            "full_registrations": merges.get("full_registrations"),
            "hinted": merges.get("hinted"),
            "merge_cpu_s_reported": merges.get("cpu_s"),
            "merging_thread_cpu_s": _delta(cpu["merging_thread"], cpu0[vid]["merging_thread"]),
            "process_cpu_s": _delta(cpu["process"], cpu0[vid]["process"]),
            "last_merge": merges.get("last"),
            "accepted": j["accepted"], "wrong": j["wrong"], "errors": j["errors"], "refused": j["refused"],
            "global_at_s": None if vid not in first_global else round(first_global[vid], 2),
            "peak_rss_mib": round(st["memory"]["peak_rss_bytes"] / 2**20, 1),
            "bytes_sent": bytes_sent(st.get("sharing") or {}),
        })
    ok = [d for d in daemons if "merges" in d]
    reported = [d["merge_cpu_s_reported"] for d in ok]
    shifts = [e[2] for d in ok for e in d["errors"].values() if len(e) > 2]
    return {
        "t_share_s": None if t_share is None else round(t_share, 2),
        "t_global_s": None if t_global is None else round(t_global, 2),
        "t_total_s": None if t_global is None or t_share is None else round(max(t_share, t_global), 2),
        "converged": t_global is not None,
        "maps_held": sum(len(d["held_maps"]) for d in ok),
        "sharing_failures": {c: sum(d["sharing_failures"].get(c, 0) for d in ok)
                             for c in sorted({c for d in ok for c in d["sharing_failures"]})},
        "merges_done": sum(d["merges"]["done"] for d in ok),
        "merges_failed": sum(d["merges"]["failed"] for d in ok),
        "merges_deferred": sum(d["merges"]["deferred"] for d in ok),
        "accepted_offsets": sum(len(d["accepted"]) for d in ok),
        "wanted_offsets": len(swarm.ids) * (len(swarm.ids) - 1),
        "wrong_merges": sum(len(d["wrong"]) for d in ok),
        "merge_cpu_s": round(sum(d["merge_cpu_s_reported"] for d in ok), 2)
        if ok and all(r is not None for r in reported) else None,
        "merging_thread_cpu_s": round(sum(d["merging_thread_cpu_s"] or 0.0 for d in ok), 2),
        "process_cpu_s": round(sum(d["process_cpu_s"] or 0.0 for d in ok), 2),
        "peak_rss_mib_max": max((d["peak_rss_mib"] for d in ok), default=None),
        "bytes_sent_per_drone": round(sum(d["bytes_sent"] for d in ok) / max(1, len(ok))),
        "displacement_m": None if not shifts else {"median": round(float(np.median(shifts)), 3),
                                                   "max": round(max(shifts), 3)},
        "daemons": daemons,
    }


def _delta(a, b):
    return None if a is None or b is None else round(a - b, 2)


# ----------------------------------------------------------------------------------- report
def table(rows: list[dict]) -> str:
    """The printed table: one line per size and mode."""
    head = ("N", "transport", "mode", "t_share", "t_global", "t_total", "maps held", "merges", "accepted",
            "wrong", "merge CPU", "proc CPU", "RSS max MiB", "CPU after", "kB sent/drone", "shift m")
    lines = ["  ".join(f"{h:>9}" for h in head)]
    for r in rows:
        t_global = f"gave up {r['gave_up_at_s']:.0f}" if r.get("gave_up_at_s") else _s(r.get("t_global_s"))
        cells = (r["drones"], r.get("transport", "mtp"), r["mode"], _s(r.get("t_share_s")), t_global,
                 _s(r.get("t_total_s")), f"{r.get('maps_held')}/{r.get('wanted_offsets')}",
                 r.get("merges_done"),
                 f"{r.get('accepted_offsets')}/{r.get('wanted_offsets')}", r.get("wrong_merges"),
                 _s(r.get("merge_cpu_s") or r.get("merging_thread_cpu_s")), _s(r.get("process_cpu_s")),
                 r.get("peak_rss_mib_max"),
                 _s((r.get("after_global") or {}).get("merging_thread_cpu_s")),
                 None if r.get("bytes_sent_per_drone") is None else round(r["bytes_sent_per_drone"] / 1000),
                 "-" if not r.get("displacement_m") else
                 f"{r['displacement_m']['median']:.2f}/{r['displacement_m']['max']:.2f}")
        lines.append("  ".join(f"{str(c):>9}" for c in cells))
    lines.append(f"thesis (§10.4, 10 drones): share {THESIS['t_share_s']} s, merge {THESIS['t_merge_s']} s, "
                 f"total {THESIS['t_total_s']} s; goal here: 10 drones <= {GOAL_TOTAL_S:.0f} s total")
    return "\n".join(lines)


def flight_description(world: str, seed: int, drones: int, camera_rate_hz: float) -> str:
    """What the maps are, said with the camera rate and whether it was reduced from the emulator's."""
    default = simset.camera().rate_hz
    rate = f"cameras at {camera_rate_hz:g} Hz" + ("" if camera_rate_hz == default else
                                                 f" (reduced from the emulator's {default:g} Hz)")
    return f"maps: simset flight of {drones} drones in {world}, seed {seed}, {rate}"


def _s(v):
    return "-" if v is None else (f"{v:.1f}" if isinstance(v, float) else str(v))


def comparisons(rows: list[dict]) -> list[dict]:
    """Per size run both ways: distributed / whole-map ratios of merge CPU and t_global."""
    out = []
    for n in sorted({r["drones"] for r in rows}):
        by = {r["mode"]: r for r in rows if r["drones"] == n and r.get("transport", "mtp") == "mtp"}
        a, b = by.get("distributed"), by.get("central")
        if a is None or b is None:
            continue
        cpu_key = "merge_cpu_s" if a.get("merge_cpu_s") and b.get("merge_cpu_s") else "merging_thread_cpu_s"
        out.append({"drones": n, "cpu": cpu_key,
                    "merge_cpu_ratio": _ratio(a.get(cpu_key), b.get(cpu_key)),
                    "t_global_ratio": _ratio(a.get("t_global_s"), b.get("t_global_s"))})
    return out


def _ratio(a, b):
    return None if not a or not b else round(a / b, 3)


def modes(extra: dict) -> list[tuple[str, dict]]:
    """(label, [merging] table) per way of merging this build offers: both when `distributed` exists."""
    names = {f.name for f in dataclasses.fields(MergingConfig)}
    if "distributed" in names:
        return [("central", extra | {"distributed": False}), ("distributed", extra | {"distributed": True})]
    return [("default", extra)]


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--drones", default="2,4,6,8,10", help="swarm sizes, comma-separated")
    ap.add_argument("--world", default="small_house")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--vehicles", type=int, default=10,
                    help="drones of the flight (at least the largest size); size N runs the first N maps")
    ap.add_argument("--camera-rate", type=float, default=None, metavar="HZ",
                    help="frame rate of every camera of the flight (default: the emulator's)")
    ap.add_argument("--timeout", type=float, default=300.0, help="seconds per size after all daemons run")
    ap.add_argument("--start-timeout", type=float, default=300.0,
                    help="seconds for all daemons of a size to run")
    ap.add_argument("--linger", type=float, default=15.0,
                    help="seconds watched after convergence (merges done then are extra)")
    ap.add_argument("--tol-m", type=float, default=0.3)
    ap.add_argument("--tol-deg", type=float, default=3.0)
    ap.add_argument("--merging", default="", help="[merging] keys for every daemon, e.g. period_s=10")
    ap.add_argument("--shared-address", action="store_true",
                    help="every daemon on 127.0.0.1 (not one loopback address each)")
    ap.add_argument("--keep", action="store_true", help="keep the daemons' directories under /tmp")
    ap.add_argument("--transport", default="mtp", help="mtp, zenoh, or both comma-separated (each runs)")
    ap.add_argument("--modes", default="", help="central, distributed or both (default: what the build has)")
    ap.add_argument("--out", default=str(ROOT / "out" / "bench" / "swarm.json"))
    args = ap.parse_args()
    sizes = [int(s) for s in args.drones.split(",")]
    if not sizes or min(sizes) < 2 or max(sizes) > 99:
        ap.error("--drones: sizes between 2 and 99")
    extra = {k: json.loads(v) for k, v in (kv.split("=", 1) for kv in filter(None, args.merging.split(",")))}
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))  # unwinds through run_size's finally
    t = time.monotonic()
    k = max(args.vehicles, max(sizes))
    try:
        camera_rate_hz = simset.camera(args.camera_rate).rate_hz
    except ValueError as e:
        ap.error(f"--camera-rate: {e}")
    flight = simset.flight_maps(args.world, args.seed, k, cache_dir=ROOT / simset.CACHE_DIR,
                                camera_rate_hz=args.camera_rate)
    maps_s = time.monotonic() - t
    maps_said = flight_description(args.world, args.seed, k, camera_rate_hz)
    print(maps_said, file=sys.stderr)
    rows = []
    transports = [t for t in args.transport.split(",") if t]
    if not set(transports) <= {"mtp", "zenoh"}:
        ap.error("--transport: mtp and/or zenoh")
    wanted = set(filter(None, args.modes.split(",")))
    for n in sizes:
        for transport in transports:
            for label, merging in modes(extra):
                if wanted and label not in wanted:
                    continue
                try:
                    row = run_size(flight[:n], merging, args, label, transport)
                except RuntimeError as e:  # a size whose daemons did not start: said, the others still run
                    row = {"drones": n, "mode": label, "transport": transport, "error": str(e)[-3000:]}
                rows.append(row)
                print(json.dumps({k: v for k, v in row.items() if k != "daemons"}), file=sys.stderr)
    result = {
        "bench": "swarm",
        "conditions": {"world": args.world, "seed": args.seed, "maps": maps_said,
                       "camera_rate_hz": camera_rate_hz, "camera_rate_default_hz": simset.camera().rate_hz,
                       "map_cells": [m.grid.size for m in flight], "maps_s": round(maps_s, 1),
                       "cpus": os.cpu_count(), "load_avg_1min": os.getloadavg()[0], "timeout_s": args.timeout,
                       "tol": [args.tol_m, args.tol_deg], "merging": extra},
        "thesis": THESIS,
        "goal_total_s_10_drones": GOAL_TOTAL_S,
        "sizes": rows,
        "comparison": comparisons(rows),
    }
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_suffix(".tmp")
    tmp.write_text(json.dumps(result, indent=1))
    tmp.replace(out)
    print(table(rows))
    print(maps_said)


if __name__ == "__main__":
    main()

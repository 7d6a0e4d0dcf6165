"""`coopctl status` and the sd_notify STATUS= line, assembled from what each stage reports.

Field names follow docs/operations.md ("Control protocol"); coopctl prints missing parts as '-'.
"""

import math
import threading
import time
from functools import cached_property

import numpy as np

from coopd.daemon.merger import NOT_AVAILABLE
from coopd.daemon.threads import ROLE_NICE, read_nice
from coopd.net import host_port


class _Reads:
    """What several sections read, each read once per status (on first use)."""

    def __init__(self, daemon):
        self.daemon = daemon

    @cached_property
    def link(self) -> dict:
        return self.daemon.link.status()

    @cached_property
    def camera(self) -> dict:
        camera = self.daemon.camera
        return camera.status() if hasattr(camera, "status") else {}

    @cached_property
    def assoc(self) -> dict:
        return self.daemon.associator.status()

    @cached_property
    def merges(self) -> dict:
        return self.daemon.merger.status()

    @cached_property
    def sharing(self) -> dict | None:
        return None if self.daemon.sharing is None else self.daemon.sharing.stats()


def _link(d, r: _Reads) -> dict:
    link = r.link
    return {
        "state": link["link"],
        "reason": link["reason"],
        "reason_detail": link["reason_detail"],
        "age_s": link["heartbeat_age_s"],
        "odometry_age_s": link["odometry_age_s"],
        "odometry_stale": link["odometry_stale"],
        "connection": link["connection"],
        "map_origin_fc_enu": link["map_origin_fc_enu"],
        "map_origin_t_fc": link["map_origin_t_fc"],
        "counters": link["counters"],
    }


def _map(d, r: _Reads) -> dict:
    grid = d.mapper.grid
    counts = grid.counts()
    return {
        "shape": list(grid.shape),
        "cells": grid.size,
        "known": counts.known,
        "occupied": counts.occupied,
        "resolution_m": grid.resolution,
        "version": d.mapper.version,
        "offset": [int(v) for v in grid.offset],
    }


def _mapping(d, r: _Reads) -> dict:
    return {
        "state": mapping_state(d, r.link, r.camera),
        "paused": r.link["frame"]["paused"],
        "frame": r.link["frame"],
        "reanchor": d.reanchor.status(),
        "frames_mapped": d.frames_mapped,
        "latency_ms": _percentiles(np.array(d.latency_s, dtype=np.float64)),
        "skipped": r.assoc["skipped"],
        "rejected": dict(d.mapper.totals.reject_reasons),
        "errors": d.mapping_errors,
    }


def _frames(d, r: _Reads) -> dict:
    return {
        "in": r.camera.get("counters", {}).get("frames", 0),
        "mapped": d.frames_mapped,
        "dropped": d.slot.dropped,
        "skipped": sum(r.assoc["skipped"].values()),
        "rejected": d.mapper.totals.frames_rejected,
    }


def _camera(d, r: _Reads) -> dict:
    counters = r.camera.get("counters", {})
    return {
        "source": d.config.camera.source,
        "connected": r.camera.get("connected"),
        "last_frame_age_s": r.camera.get("last_frame_age_s"),
        "stalls": counters.get("disconnect_stall", 0),
        "reconnects": max(0, counters.get("connects", 0) - 1),
        "counters": counters,
    }


def _watchdog(d, r: _Reads) -> dict:
    return {
        "interval_s": d.watchdog.interval,
        "pings": d.watchdog.pings,
        "withheld": d.watchdog.withheld,
        "healthy": d.healthy(),
        "watched_threads": d.progress.watched(),
        "stalled_threads": d.stalled_threads(),
        "notify_sent": d.notifier.sent,
        "notify_dropped": d.notifier.dropped,
    }


SECTIONS = {
    "link": _link,
    "pose": lambda d, r: pose(d.link, r.link),
    "map": _map,
    "mapping": _mapping,
    "frames": _frames,
    "camera": _camera,
    "peers": lambda d, r: peers(d, r.sharing),
    "sharing": lambda d, r: None if r.sharing is None else _jsonable(r.sharing),
    "merges": lambda d, r: r.merges,
    "merging": lambda d, r: r.merges["state"],
    "obstacles": lambda d, r: ({"enabled": False, "when_fc_asks": False, "sending": False, "fc": "not asked"}
                               if d.obstacles is None else d.obstacles.status()),
    "viewer": lambda d, r: {"enabled": False} if d.viewer is None else d.viewer.status(),
    "memory": lambda d, r: {**d.budget.snapshot(), **d.rss_watch.status()},
    "threads": lambda d, r: threads(d),
    "control": lambda d, r: d.control.stats(),
    "checkpoint": lambda d, r: {**d.store.stats(), "versions_reserved": d.versions.reserved,
                                "version_reserve_failed": d.versions.failed},
    "watchdog": _watchdog,
}
"""The status sections by name, in the order of the reply: `status` with args {"sections": [...]}
builds only those (a monitor polling many daemons asks for what it reads; the whole status of a
drone with 29 peers costs it milliseconds of CPU)."""


def check_sections(names) -> frozenset[str] | None:
    """The section names a status request asks for (None: all); ValueError naming the unknown ones."""
    if names is None:
        return None
    if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
        raise ValueError("sections must be a list of section names")
    unknown = sorted(set(names) - SECTIONS.keys())
    if unknown:
        raise ValueError(f"unknown status sections {unknown}; known: {', '.join(SECTIONS)}")
    return frozenset(names)


def build(daemon, sections: frozenset[str] | None = None) -> dict:
    """The status of a running Daemon as plain JSON data: who it is, and every section (or those
    named in `sections`, see check_sections)."""
    reads = _Reads(daemon)
    out = {
        "vehicle_id": daemon.vehicle_id,
        "pid": daemon.pid,
        "state": daemon.state,
        "uptime_s": round(time.monotonic() - daemon.started, 1),
    }
    for name, part in SECTIONS.items():
        if sections is None or name in sections:
            out[name] = part(daemon, reads)
    return out


def mapping_state(daemon, link: dict, camera: dict) -> str:
    """mapping, or why not: odometry stale (link lost) pauses it, a silent camera starves it."""
    if link["odometry_stale"]:
        return f"paused: odometry stale (link {link['link']})"
    if link["frame"]["paused"]:
        return f"paused: {link['frame']['paused']}"
    age = camera.get("last_frame_age_s")
    if age is None or age > daemon.config.camera.stall_timeout_s:
        return "waiting for camera frames"
    return "mapping"


def pose(link_obj, link: dict) -> dict | None:
    latest = link_obj.poses.latest()
    if latest is None:
        return None
    w, x, y, z = (float(v) for v in latest.quaternion)
    yaw = math.degrees(math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z)))
    return {
        "position_m": [round(float(v), 3) for v in latest.position],
        "yaw_deg": round(yaw, 2),
        "age_s": link["odometry_age_s"],
        "t_fc": latest.t_fc,
    }


def peers(daemon, sharing: dict | None) -> list[dict]:
    """One entry per peer vehicle, in coopctl's format, from the sharing stats (SharingService.stats);
    where each peer's map sits in ours is in merges.offsets."""
    if sharing is None:
        return []
    out = []
    for p in sharing["peers"]:
        vid = p["vehicle_id"]
        stored = daemon.sharing.received.get(vid) if vid is not None else None
        out.append(
            {
                "vehicle_id": vid,
                "address": host_port(p["address"], p["port"]) if p.get("port") else p.get("address"),
                "connected": p["connected"],
                "map_version": None if stored is None else stored.version,
                "map_bytes": None if stored is None else len(stored.data),
                "last_seen_s": p["last_seen_ago_s"],
                "maps_sent": p["maps_sent"],
                "maps_received": p["maps_received"],
                "deltas_sent": p["deltas_sent"],
                "wire_bytes_sent": p["wire_bytes_sent"],
                "failures": p["failures"],
            }
        )
    return sorted(out, key=lambda p: (p["vehicle_id"] is None, p["vehicle_id"] or 0))


def threads(daemon) -> list[dict]:
    """Role threads (priority applied by themselves) and the sharing service's threads, which
    inherit the nice of coopd-sharing that started them."""
    out = daemon.priorities.report()
    for t in threading.enumerate():
        if t.name.startswith("coopd-share") and t.native_id is not None:
            try:
                nice = read_nice(t.native_id)
            except (OSError, ValueError, IndexError):
                continue
            out.append(
                {"role": "sharing", "thread": t.name, "tid": t.native_id, "requested": ROLE_NICE["sharing"],
                 "applied": nice, "note": "" if nice == ROLE_NICE["sharing"] else "inherited"}
            )
    return out


def global_note(daemon) -> str:
    m = daemon.merger
    if not m.available:
        return f"{NOT_AVAILABLE}: the global map is the local map"
    return "no merge yet: the global map is the local map"


def summary(daemon) -> str:
    """One short line for sd_notify STATUS= (systemctl status shows it)."""
    grid = daemon.mapper.grid
    why = daemon.link.reason()
    link = daemon.link.state + ("" if why is None else f" ({why[0]})")
    paused = " (paused: odometry stale)" if daemon.link.odometry_stale() else ""
    note = daemon.link.frames.note()
    paused = paused or ("" if note is None else f" ({note})")
    n_peers = 0 if daemon.sharing is None else len(daemon.sharing.peers.vehicle_ids())
    m = daemon.merger
    merges = f"merges {m.counters['done']}/{m.counters['failed']}/{m.counters['deferred']}"
    if not m.available:
        merges = "merging n/a"
    return (
        f"{daemon.state}: link {link}, {daemon.frames_mapped} frames mapped{paused}, "
        f"map v{daemon.mapper.version} {'x'.join(map(str, grid.shape))}, {n_peers} peers, {merges}"
    )


def log_line(daemon) -> str:
    """The periodic operator log line: the STATUS summary plus latency, drops and memory."""
    lat = _percentiles(np.array(daemon.latency_s, dtype=np.float64))
    return (
        f"{summary(daemon)}; latency p50 {lat['p50']} ms p99 {lat['p99']} ms over {lat['n']} frames, "
        f"{daemon.slot.dropped} frames dropped, {daemon.mapper.grid.counts().known} known cells, "
        f"RSS {daemon.budget.rss() / 2**20:.0f} of {daemon.budget.budget_bytes / 2**20:.0f} MiB"
    )


def _percentiles(values: np.ndarray) -> dict:
    if values.size == 0:
        return {"n": 0, "p50": None, "p99": None, "max": None}
    return {
        "n": int(values.size),
        "p50": round(1e3 * float(np.percentile(values, 50)), 2),
        "p99": round(1e3 * float(np.percentile(values, 99)), 2),
        "max": round(1e3 * float(values.max()), 2),
    }


def _jsonable(value):
    """Dict keys as strings (JSON), recursively."""
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    return value

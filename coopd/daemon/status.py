"""`coopctl status` and the sd_notify STATUS= line, assembled from what each stage reports.

Field names follow docs/operations.md ("Control protocol"); coopctl prints missing parts as '-'.
"""

import math
import threading
import time

import numpy as np

from coopd.daemon.merger import NOT_AVAILABLE
from coopd.daemon.threads import ROLE_NICE, read_nice
from coopd.net import host_port


def build(daemon) -> dict:
    """The whole status of a running Daemon as plain JSON data."""
    link = daemon.link.status()
    camera = daemon.camera.status() if hasattr(daemon.camera, "status") else {}
    cam_counters = camera.get("counters", {})
    mapper = daemon.mapper
    grid = mapper.grid
    counts = grid.counts()
    assoc = daemon.associator.status()
    lat = np.array(daemon.latency_s, dtype=np.float64)
    merges = daemon.merger.status()
    sharing = None if daemon.sharing is None else daemon.sharing.stats()
    return {
        "vehicle_id": daemon.vehicle_id,
        "pid": daemon.pid,
        "state": daemon.state,
        "uptime_s": round(time.monotonic() - daemon.started, 1),
        "link": {
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
        },
        "pose": pose(daemon.link, link),
        "map": {
            "shape": list(grid.shape),
            "cells": grid.size,
            "known": counts.known,
            "occupied": counts.occupied,
            "resolution_m": grid.resolution,
            "version": mapper.version,
            "offset": [int(v) for v in grid.offset],
        },
        "mapping": {
            "state": mapping_state(daemon, link, camera),
            "paused": link["frame"]["paused"],
            "frame": link["frame"],
            "reanchor": daemon.reanchor.status(),
            "frames_mapped": daemon.frames_mapped,
            "latency_ms": _percentiles(lat),
            "skipped": assoc["skipped"],
            "rejected": dict(mapper.totals.reject_reasons),
            "errors": daemon.mapping_errors,
        },
        "frames": {
            "in": cam_counters.get("frames", 0),
            "mapped": daemon.frames_mapped,
            "dropped": daemon.slot.dropped,
            "skipped": sum(assoc["skipped"].values()),
            "rejected": mapper.totals.frames_rejected,
        },
        "camera": {
            "source": daemon.config.camera.source,
            "connected": camera.get("connected"),
            "last_frame_age_s": camera.get("last_frame_age_s"),
            "stalls": cam_counters.get("disconnect_stall", 0),
            "reconnects": max(0, cam_counters.get("connects", 0) - 1),
            "counters": cam_counters,
        },
        "peers": peers(daemon, sharing),
        "sharing": None if sharing is None else _jsonable(sharing),
        "merges": merges,
        "merging": merges["state"],
        "obstacles": ({"enabled": False, "when_fc_asks": False, "sending": False, "fc": "not asked"}
                      if daemon.obstacles is None else daemon.obstacles.status()),
        "viewer": {"enabled": False} if daemon.viewer is None else daemon.viewer.status(),
        "memory": {**daemon.budget.snapshot(), **daemon.rss_watch.status()},
        "threads": threads(daemon),
        "control": daemon.control.stats(),
        "checkpoint": {**daemon.store.stats(), "versions_reserved": daemon.versions.reserved,
                       "version_reserve_failed": daemon.versions.failed},
        "watchdog": {
            "interval_s": daemon.watchdog.interval,
            "pings": daemon.watchdog.pings,
            "withheld": daemon.watchdog.withheld,
            "healthy": daemon.healthy(),
            "watched_threads": daemon.progress.watched(),
            "stalled_threads": daemon.stalled_threads(),
            "notify_sent": daemon.notifier.sent,
            "notify_dropped": daemon.notifier.dropped,
        },
    }


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

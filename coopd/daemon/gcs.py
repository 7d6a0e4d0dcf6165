"""What the flight controller and the GCS learn about coopd: HEARTBEAT system_status following the
daemon's health, and one STATUSTEXT per event that matters (FC link up and lost, odometry ok and
lost, camera frames ok and stalled, mapping paused and resumed after the FC's frame moved (a reboot or an
estimator reset), a peer's map merged), sent through the FC link (rate-limited there).

| system_status | when |
|---|---|
| BOOT | the daemon is starting |
| STANDBY | running, not mapping yet, nothing failed (no odometry or no camera frame so far) |
| ACTIVE | mapping: fresh odometry and camera frames |
| CRITICAL | mapping stopped: odometry or camera frames failed, or the FC's frame moved (not re-anchored) |
"""

from __future__ import annotations

from dataclasses import dataclass, field

from pymavlink.dialects.v20 import common as mav


@dataclass(frozen=True)
class Health:
    """What the events are computed from (one sample of the daemon's main loop)."""

    link_ok: bool
    odometry_fresh: bool
    camera_fresh: bool
    camera_age_s: float | None = None
    merged: frozenset[int] = field(default_factory=frozenset)
    """Vehicles whose maps are in the global map (accepted and confirmed)."""
    frame_note: str | None = None
    """Why mapping is paused after the FC's frame moved (FrameContinuity.note), or None."""


def health_events(prev: Health | None, cur: Health) -> list[tuple[int, str]]:
    """(MAV_SEVERITY, text) for every change from prev to cur that the GCS should hear about."""
    if prev is None:
        return []
    out = []
    if prev.link_ok and not cur.link_ok:
        out.append((mav.MAV_SEVERITY_WARNING, "coopd: FC link lost"))
    elif cur.link_ok and not prev.link_ok:
        out.append((mav.MAV_SEVERITY_NOTICE, "coopd: FC link up"))
    if prev.odometry_fresh and not cur.odometry_fresh:
        out.append((mav.MAV_SEVERITY_WARNING, "coopd: no odometry, mapping paused"))
    elif cur.odometry_fresh and not prev.odometry_fresh:
        out.append((mav.MAV_SEVERITY_NOTICE, "coopd: odometry ok"))
    if prev.camera_fresh and not cur.camera_fresh:
        age = "" if cur.camera_age_s is None else f", no frame for {cur.camera_age_s:.0f} s"
        out.append((mav.MAV_SEVERITY_WARNING, f"coopd: camera stalled{age}"))
    elif cur.camera_fresh and not prev.camera_fresh:
        out.append((mav.MAV_SEVERITY_NOTICE, "coopd: camera frames ok"))
    if cur.frame_note and not prev.frame_note:
        out.append((mav.MAV_SEVERITY_WARNING, f"coopd: {cur.frame_note}"))
    elif prev.frame_note and not cur.frame_note:
        out.append((mav.MAV_SEVERITY_NOTICE, "coopd: map frame re-anchored, mapping"))
    for vid in sorted(cur.merged - prev.merged):
        out.append((mav.MAV_SEVERITY_INFO, f"coopd: merge confirmed for vehicle {vid}"))
    return out


def system_status(cur: Health, odometry_seen: bool, camera_seen: bool) -> int:
    """MAV_STATE for our HEARTBEAT (the table above); *_seen: that input was fresh at least once."""
    if cur.frame_note:
        return mav.MAV_STATE_CRITICAL
    if cur.odometry_fresh and cur.camera_fresh:
        return mav.MAV_STATE_ACTIVE
    failed = (odometry_seen and not cur.odometry_fresh) or (camera_seen and not cur.camera_fresh)
    return mav.MAV_STATE_CRITICAL if failed else mav.MAV_STATE_STANDBY


class GcsReporter:
    """Owns the previous health sample; update() sets the link's system_status and sends the events."""

    def __init__(self, link):
        self.link = link
        self.prev = Health(link_ok=False, odometry_fresh=False, camera_fresh=False)
        """Nothing works before the first sample: the GCS hears the link, odometry and camera come up."""
        self.odometry_seen = False
        self.camera_seen = False
        link.system_status = mav.MAV_STATE_BOOT

    def update(self, cur: Health) -> None:
        self.odometry_seen |= cur.odometry_fresh
        self.camera_seen |= cur.camera_fresh
        for severity, text in health_events(self.prev, cur):
            self.link.statustext(severity, text)
        self.link.system_status = system_status(cur, self.odometry_seen, self.camera_seen)
        self.prev = cur

"""MAVLink mission protocol, server side: upload, download, clear, set-current, with retries."""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np
from pymavlink.dialects.v20 import common as mav

from firmware_sim.flight import NAV_LAND, NAV_TAKEOFF, NavTarget

MAX_ITEMS = 1000
REQUEST_TIMEOUT_WALL_S = 1.0
REQUEST_RETRIES = 5
GLOBAL_FRAMES = {
    mav.MAV_FRAME_GLOBAL,
    mav.MAV_FRAME_GLOBAL_RELATIVE_ALT,
    mav.MAV_FRAME_GLOBAL_INT,
    mav.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
    mav.MAV_FRAME_GLOBAL_TERRAIN_ALT,
    mav.MAV_FRAME_GLOBAL_TERRAIN_ALT_INT,
}
AMSL_FRAMES = {mav.MAV_FRAME_GLOBAL, mav.MAV_FRAME_GLOBAL_INT}


@dataclass(frozen=True)
class MissionItem:
    """One stored mission item, in MISSION_ITEM_INT form (x, y as sent: 1e7 deg or 1e4 m)."""

    seq: int
    frame: int
    command: int
    current: int
    autocontinue: int
    param1: float
    param2: float
    param3: float
    param4: float
    x: int
    y: int
    z: float
    mission_type: int = 0


def item_from_message(msg) -> MissionItem:
    """Normalise MISSION_ITEM_INT or the legacy float MISSION_ITEM into a MissionItem."""
    x, y = msg.x, msg.y
    if msg.get_type() == "MISSION_ITEM":
        factor = 1e7 if msg.frame in GLOBAL_FRAMES else 1e4
        x = int(round(x * factor)) if math.isfinite(x) else 0
        y = int(round(y * factor)) if math.isfinite(y) else 0
    return MissionItem(
        msg.seq,
        msg.frame,
        msg.command,
        msg.current,
        msg.autocontinue,
        msg.param1,
        msg.param2,
        msg.param3,
        msg.param4,
        int(x),
        int(y),
        float(msg.z),
        getattr(msg, "mission_type", 0),
    )


def nav_target(item: MissionItem, lla_to_local, home_z: float) -> NavTarget:
    """Convert a stored item into an executable local-ENU target (NaN components = keep current)."""
    pos = None
    if item.frame in GLOBAL_FRAMES:
        has_xy = not (item.x == 0 and item.y == 0)
        z = item.z if math.isfinite(item.z) else math.nan
        if item.frame in AMSL_FRAMES:
            local = lla_to_local(item.x * 1e-7, item.y * 1e-7, z)
            z_local = local[2]
        else:
            local = lla_to_local(item.x * 1e-7, item.y * 1e-7, 0.0)
            z_local = home_z + z
        pos = np.array([local[0] if has_xy else math.nan, local[1] if has_xy else math.nan, z_local])
    elif item.frame in (mav.MAV_FRAME_LOCAL_NED, mav.MAV_FRAME_LOCAL_ENU):
        xm, ym = item.x * 1e-4, item.y * 1e-4
        if item.frame == mav.MAV_FRAME_LOCAL_NED:
            pos = np.array([ym, xm, -item.z])
        else:
            pos = np.array([xm, ym, item.z])
    if item.command == NAV_TAKEOFF and pos is not None:
        pos = np.array([math.nan, math.nan, pos[2]])
    if item.command == NAV_LAND and pos is not None and not np.all(np.isfinite(pos[:2])):
        pos = None
    if item.command == NAV_LAND and pos is not None:
        pos = np.array([pos[0], pos[1], math.nan])
    hold = item.param1 if item.command in (16, 19) and math.isfinite(item.param1) else 0.0
    speed = item.param2 if item.command == 178 and math.isfinite(item.param2) and item.param2 > 0 else None
    return NavTarget(item.seq, item.command, pos=pos, hold_s=max(0.0, min(3600.0, hold)), speed=speed)


class MissionServer:
    """Holds the uploaded plans per mission type and runs the transfer state machine."""

    def __init__(self, link) -> None:
        self.link = link
        self.plans: dict[int, list[MissionItem]] = {0: [], 1: [], 2: []}
        self.upload: dict | None = None
        self.current_seq = 0

    def handle(self, msg) -> bool:
        """Process a mission-protocol message; True if it was one."""
        t = msg.get_type()
        handler = getattr(self, "_on_" + t.lower(), None)
        if handler is None:
            return False
        handler(msg)
        return True

    def _ack(self, msg, result: int, mission_type: int) -> None:
        """Send MISSION_ACK to the sender."""
        self.link.send(
            self.link.tx.mission_ack_encode(msg.get_srcSystem(), msg.get_srcComponent(), result, mission_type)
        )

    def _on_mission_count(self, msg) -> None:
        """Start an upload: request item 0 (or accept an empty plan)."""
        mtype = getattr(msg, "mission_type", 0)
        if mtype not in self.plans:
            self._ack(msg, mav.MAV_MISSION_UNSUPPORTED, mtype)
            return
        if msg.count > MAX_ITEMS:
            self._ack(msg, mav.MAV_MISSION_NO_SPACE, mtype)
            return
        if msg.count == 0:
            self._store(mtype, [])
            self._ack(msg, mav.MAV_MISSION_ACCEPTED, mtype)
            return
        self.upload = {
            "type": mtype,
            "count": msg.count,
            "items": [],
            "peer": (msg.get_srcSystem(), msg.get_srcComponent()),
            "retries": 0,
        }
        self._request_next()

    def _request_next(self) -> None:
        """Ask the uploader for the next item."""
        u = self.upload
        u["sent"] = time.monotonic()
        self.link.send(
            self.link.tx.mission_request_int_encode(u["peer"][0], u["peer"][1], len(u["items"]), u["type"])
        )

    def _on_mission_item_int(self, msg) -> None:
        """Receive one uploaded item; out-of-sequence items are ignored (the request is re-sent)."""
        u = self.upload
        mtype = getattr(msg, "mission_type", 0)
        if u is None or mtype != u["type"] or msg.seq != len(u["items"]):
            self.link.stats["mission_out_of_sequence"] += 1
            return
        u["items"].append(item_from_message(msg))
        u["retries"] = 0
        if len(u["items"]) < u["count"]:
            self._request_next()
            return
        self.upload = None
        self._store(mtype, u["items"])
        self._ack(msg, mav.MAV_MISSION_ACCEPTED, mtype)

    _on_mission_item = _on_mission_item_int

    def _store(self, mtype: int, items: list[MissionItem]) -> None:
        """Keep a finished plan; a new flight plan becomes the vehicle's mission."""
        self.plans[mtype] = items
        if mtype == 0:
            self.current_seq = 0
            self.link.load_mission(items)

    def _on_mission_request_list(self, msg) -> None:
        """Start a download: announce the count."""
        mtype = getattr(msg, "mission_type", 0)
        if mtype not in self.plans:
            self._ack(msg, mav.MAV_MISSION_UNSUPPORTED, mtype)
            return
        self.link.send(
            self.link.tx.mission_count_encode(
                msg.get_srcSystem(), msg.get_srcComponent(), len(self.download_plan(mtype)), mtype
            )
        )

    def download_plan(self, mtype: int) -> list[MissionItem]:
        """The items a download of this mission type returns (an autopilot may add its own)."""
        return self.plans[mtype]

    def _on_mission_request_int(self, msg) -> None:
        """Send one requested item of a download."""
        mtype = getattr(msg, "mission_type", 0)
        plan = self.download_plan(mtype) if mtype in self.plans else None
        if plan is None or not 0 <= msg.seq < len(plan):
            self._ack(msg, mav.MAV_MISSION_INVALID_SEQUENCE, mtype)
            return
        it = plan[msg.seq]
        self.link.send(
            self.link.tx.mission_item_int_encode(
                msg.get_srcSystem(),
                msg.get_srcComponent(),
                it.seq,
                it.frame,
                it.command,
                int(it.seq == self.current_seq),
                it.autocontinue,
                it.param1,
                it.param2,
                it.param3,
                it.param4,
                it.x,
                it.y,
                it.z,
                mtype,
            )
        )

    _on_mission_request = _on_mission_request_int

    def _on_mission_ack(self, msg) -> None:
        """The end of a download, or an uploader giving up."""
        if self.upload is not None and (msg.get_srcSystem(), msg.get_srcComponent()) == self.upload["peer"]:
            self.upload = None

    def _on_mission_clear_all(self, msg) -> None:
        """Delete a plan."""
        mtype = getattr(msg, "mission_type", 0)
        if mtype == mav.MAV_MISSION_TYPE_ALL:
            for k in self.plans:
                self._store(k, [])
        elif mtype in self.plans:
            self._store(mtype, [])
        else:
            self._ack(msg, mav.MAV_MISSION_UNSUPPORTED, mtype)
            return
        self._ack(msg, mav.MAV_MISSION_ACCEPTED, mtype)

    def _on_mission_set_current(self, msg) -> None:
        """Jump to another item of the flight plan."""
        if 0 <= msg.seq < len(self.plans[0]):
            self.current_seq = msg.seq
            self.link.set_current(msg.seq)
        else:
            self.link.send(self.link.tx.statustext_encode(4, b"Mission set current: invalid sequence"))

    def tick(self) -> None:
        """Re-request an upload item after a timeout; abandon the upload after a few retries."""
        u = self.upload
        if u is None or time.monotonic() - u["sent"] < REQUEST_TIMEOUT_WALL_S:
            return
        if u["retries"] >= REQUEST_RETRIES:
            self.link.stats["mission_upload_timeouts"] += 1
            self.link.send(
                self.link.tx.mission_ack_encode(
                    u["peer"][0], u["peer"][1], mav.MAV_MISSION_OPERATION_CANCELLED, u["type"]
                )
            )
            self.upload = None
            return
        u["retries"] += 1
        self._request_next()

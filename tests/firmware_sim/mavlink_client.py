"""A small pymavlink client for the tests: connect, wait for messages, send commands and missions."""

from __future__ import annotations

import time

from pymavlink import mavutil
from pymavlink.dialects.v20 import common as mav


class Client:
    """Listens on 127.0.0.1:port like a GCS/companion (udpin) and replies to the vehicle's address."""

    def __init__(self, port: int, target_system: int = 1):
        self.conn = mavutil.mavlink_connection(
            f"udpin:127.0.0.1:{port}", source_system=245, source_component=190, dialect="common"
        )
        self.target = target_system

    @property
    def mav(self):
        return self.conn.mav

    def wait(self, mtype, pred=lambda m: True, timeout: float = 5.0):
        """Next message of a type matching pred, or None after timeout (wall seconds)."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            m = self.conn.recv_match(type=mtype, blocking=True, timeout=0.2)
            if m is not None and m.get_srcSystem() == self.target and pred(m):
                return m
        return None

    def collect(self, seconds: float) -> list:
        """Every message received from the target during a wall-time window."""
        out, deadline = [], time.monotonic() + seconds
        while time.monotonic() < deadline:
            m = self.conn.recv_match(blocking=True, timeout=0.1)
            if m is not None and m.get_srcSystem() == self.target:
                out.append(m)
        return out

    def drain(self, limit: int = 100_000) -> list:
        """Read everything already queued (so a full socket buffer cannot drop the next reply)."""
        out = []
        for _ in range(limit):
            m = self.conn.recv_match(blocking=False)
            if m is None:
                break
            out.append(m)
        return out

    def command(self, command: int, *params: float, timeout: float = 3.0):
        """COMMAND_LONG with up to 7 params; returns the matching COMMAND_ACK's result (or None)."""
        self.drain()
        p = list(params) + [0.0] * (7 - len(params))
        self.mav.command_long_send(self.target, 1, command, 0, *p)
        ack = self.wait("COMMAND_ACK", lambda m: m.command == command, timeout)
        return None if ack is None else ack.result

    def set_mode(self, main: int, sub: int = 0):
        """PX4 custom mode via MAV_CMD_DO_SET_MODE."""
        return self.command(mav.MAV_CMD_DO_SET_MODE, mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, main, sub)

    def upload_mission(self, items: list[dict], timeout: float = 10.0) -> int:
        """Mission upload protocol (MISSION_INT); returns the final MISSION_ACK type."""
        self.mav.mission_count_send(self.target, 1, len(items), 0)
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            m = self.conn.recv_match(
                type=["MISSION_REQUEST_INT", "MISSION_REQUEST", "MISSION_ACK"], blocking=True, timeout=0.5
            )
            if m is None:
                continue
            if m.get_type() == "MISSION_ACK":
                return m.type
            it = items[m.seq]
            self.mav.mission_item_int_send(
                self.target,
                1,
                m.seq,
                it["frame"],
                it["command"],
                0,
                1,
                it.get("p1", 0),
                it.get("p2", 0),
                0,
                it.get("p4", float("nan")),
                it.get("x", 0),
                it.get("y", 0),
                it.get("z", 0),
                0,
            )
        raise TimeoutError("mission upload did not finish")

"""The camera socket protocol (docs/camera-protocol.md): header parsing and validation only."""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass

import msgpack

from ..mapping.sensor import FrameRejected, Intrinsics

LENGTH = struct.Struct("<I")
MAX_HEADER = 4096
MAX_SIDE = 4096
VERSION = 1
INT_FIELDS = ("v", "seq", "t_us", "w", "h", "n")
FLOAT_FIELDS = ("fx", "fy", "cx", "cy", "scale", "min_m", "max_m")
CLOCK_FC = "fc"
CLOCK_MONOTONIC = "monotonic"
CLOCKS = (CLOCK_FC, CLOCK_MONOTONIC)
"""Time domains of `t_us`: the flight controller's boot clock (the default when `clock` is absent) or
this host's CLOCK_MONOTONIC (Python's time.monotonic()), which coopd converts with its FC clock fit."""


class ProtocolError(ValueError):
    """The byte stream broke the protocol; `reason` is a short counter key. The connection is dropped."""

    def __init__(self, reason: str, detail: str):
        super().__init__(f"{reason}: {detail}")
        self.reason = reason


@dataclass(frozen=True)
class FrameHeader:
    """A header that passed every check; `n` payload bytes follow it."""

    seq: int
    t_us: int
    intrinsics: Intrinsics
    min_m: float
    max_m: float
    n: int
    clock: str = CLOCK_FC


def header_length(prefix: bytes) -> int:
    """The announced header size from the 4-byte prefix; ProtocolError outside 1..MAX_HEADER."""
    (h,) = LENGTH.unpack(prefix)
    if not 1 <= h <= MAX_HEADER:
        raise ProtocolError("bad_header_length", f"header length {h} outside 1..{MAX_HEADER}")
    return h


def parse_header(raw: bytes, max_payload: int) -> FrameHeader:
    """Decode and check a msgpack header (types, ranges, n == w*h*2 <= max_payload)."""
    try:
        d = msgpack.unpackb(raw, raw=False, use_list=False, strict_map_key=True)
    except Exception as e:  # msgpack raises several types on garbage (ExtraData, FormatError, ValueError, …)
        raise ProtocolError("bad_msgpack", type(e).__name__) from None
    if not isinstance(d, dict):
        raise ProtocolError("bad_header", "header is not a map")
    for k in INT_FIELDS:
        if type(d.get(k)) is not int:
            raise ProtocolError("bad_header", f"field {k!r} missing or not an integer")
    for k in FLOAT_FIELDS:
        v = d.get(k)
        if type(v) not in (int, float) or not math.isfinite(v):
            raise ProtocolError("bad_header", f"field {k!r} missing or not a finite number")
    if d["v"] != VERSION:
        raise ProtocolError("bad_version", f"protocol version {d['v']} (expected {VERSION})")
    if d.get("enc") != "z16":
        raise ProtocolError("bad_encoding", f"encoding {str(d.get('enc'))[:16]!r} (expected 'z16')")
    w, h, n = d["w"], d["h"], d["n"]
    if not (1 <= w <= MAX_SIDE and 1 <= h <= MAX_SIDE):
        raise ProtocolError("bad_size", f"image {w}x{h} outside 1..{MAX_SIDE}")
    if n != w * h * 2:
        raise ProtocolError("bad_size", f"payload n={n} != w*h*2={w * h * 2}")
    if n > max_payload:
        raise ProtocolError("oversize", f"payload {n} bytes exceeds the configured {max_payload}")
    clock = d.get("clock", CLOCK_FC)
    if clock not in CLOCKS:
        raise ProtocolError("bad_clock", f"clock {str(clock)[:16]!r} (expected 'fc' or 'monotonic')")
    if d["seq"] < 0 or d["t_us"] <= 0:
        raise ProtocolError("bad_header", f"seq {d['seq']} / t_us {d['t_us']} not positive")
    if not (0.0 <= d["min_m"] < d["max_m"] <= 1000.0):
        raise ProtocolError("bad_header", f"range {d['min_m']}..{d['max_m']} m invalid")
    try:
        intr = Intrinsics(
            w, h, float(d["fx"]), float(d["fy"]), float(d["cx"]), float(d["cy"]), float(d["scale"])
        )
    except FrameRejected as e:
        raise ProtocolError("bad_intrinsics", str(e)) from None
    return FrameHeader(d["seq"], d["t_us"], intr, float(d["min_m"]), float(d["max_m"]), n, clock)

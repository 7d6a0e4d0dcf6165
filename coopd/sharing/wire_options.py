"""The wire format's encodings and decode limits without numpy, so coopctl's parser can start fast."""

from dataclasses import dataclass

ENCODINGS = {"raw": 0, "thesis": 1, "thesis-zstd": 2, "planes-zstd": 3}
"""Payload encodings of the coopd map message, by name -> id (docs/protocol.md)."""
ENCODING_NAMES = {v: k for k, v in ENCODINGS.items()}
DEFAULT_ENCODING = "planes-zstd"
ENCODING_PREFERENCE = ("planes-zstd", "thesis-zstd", "thesis", "raw")
"""Our order of preference when negotiating with a peer; "thesis" is what every coopd reads."""

MSG_MAP_DELTA = 4
"""Message type of a map delta (coopd.sharing.delta): a map as the bricks changed since a base version."""
BRICK_EDGES = (4, 8, 16, 32, 64)
"""Cells per brick edge a map delta (wire type 4) may use."""
DEFAULT_BRICK_EDGE = 8
"""8³ = 512 cells (0.8 m at 10 cm): the brick of the deltas coopd sends (scripts/bench share --delta)."""


@dataclass(frozen=True)
class DecodeLimits:
    """Upper bounds a received message must respect before anything is allocated for it."""

    max_cells: int = 400_000_000
    max_bytes: int = 512 * 1024 * 1024


DEFAULT_LIMITS = DecodeLimits()

"""The wire format's encodings and decode limits without numpy, so coopctl's parser can start fast."""

from dataclasses import dataclass

ENCODINGS = {"raw": 0, "thesis": 1, "thesis-zstd": 2, "planes-zstd": 3}
"""Payload encodings of the coopd map message, by name -> id (docs/protocol.md)."""
ENCODING_NAMES = {v: k for k, v in ENCODINGS.items()}
DEFAULT_ENCODING = "planes-zstd"
ENCODING_PREFERENCE = ("planes-zstd", "thesis-zstd", "thesis", "raw")
"""Our order of preference when negotiating with a peer; "thesis" is what every coopd reads."""


@dataclass(frozen=True)
class DecodeLimits:
    """Upper bounds a received message must respect before anything is allocated for it."""

    max_cells: int = 400_000_000
    max_bytes: int = 512 * 1024 * 1024


DEFAULT_LIMITS = DecodeLimits()

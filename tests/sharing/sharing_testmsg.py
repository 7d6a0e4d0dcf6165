"""A tiny test-only map message (not a wire format): lets transport tests run without the codec.

Layout (little-endian): b"T", uint32 vehicle id, int64 version, uint32 payload size, payload.
"""

import struct

from coopd.sharing.peers import MessageSummary

HEADER = struct.Struct("<cIqI")


def make(vehicle_id: int, version: int, payload: bytes = b"", size: int | None = None) -> bytes:
    """A test message; `size` overrides the announced payload size (to build lying headers)."""
    return HEADER.pack(b"T", vehicle_id, version, len(payload) if size is None else size) + payload


def inspect(data) -> MessageSummary:
    """The summary the transport needs; ValueError on anything that is not a test message."""
    data = memoryview(data)
    if len(data) < HEADER.size or bytes(data[:1]) != b"T":
        raise ValueError("not a test message")
    _, vid, version, size = HEADER.unpack_from(data)
    return MessageSummary(vehicle_id=vid, version=version, size=HEADER.size + size, cells=size)


def payload(data) -> bytes:
    return bytes(data[HEADER.size:])

"""Shared fixtures for firmware_sim tests: free loopback port blocks for MAVLink and cameras."""

from __future__ import annotations

import itertools
import socket

import pytest

from tests.ports import process_slot

# 14640+ keeps clear of PX4 SITL's 14540 block; the slot spreads parallel sessions and workers apart.
_BLOCKS = itertools.count(14640 + process_slot(40) * 25, 5)


def _block_is_free(base: int, size: int) -> bool:
    """True if UDP and TCP ports base..base+size-1 can all be bound on 127.0.0.1 right now."""
    for port in range(base, base + size):
        for kind in (socket.SOCK_DGRAM, socket.SOCK_STREAM):
            with socket.socket(socket.AF_INET, kind) as s:
                try:
                    s.bind(("127.0.0.1", port))
                except OSError:
                    return False
    return True


@pytest.fixture
def port_block() -> int:
    """A base port with five consecutive free ports reserved for this test."""
    for _ in range(200):
        base = next(_BLOCKS)
        if base + 5 > 65535:
            break
        if _block_is_free(base, 5):
            return base
    pytest.fail("no free block of loopback ports")

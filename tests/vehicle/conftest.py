"""Vehicle-test setup: a loopback UDP port block of our own (15100-15199)."""

import itertools

import pytest

from tests.ports import process_slot

_PORTS = itertools.count(15100 + process_slot(2) * 50, 2)  # two ports per test (multi-vehicle)


@pytest.fixture
def udp_port() -> int:
    """A fresh loopback UDP port (and the one after it) in this engineer's range, for one test."""
    return next(_PORTS)

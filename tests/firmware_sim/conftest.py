"""Shared fixtures for firmware_sim tests: unique loopback port blocks, MAVLink client helpers."""

from __future__ import annotations

import itertools
import os

import pytest

# 14640+ keeps clear of PX4 SITL's 14540 block; the pid offset keeps parallel sessions apart.
_PORTS = itertools.count(14640 + (os.getpid() % 40) * 25, 5)


@pytest.fixture
def port_block() -> int:
    """A fresh base port with five consecutive ports reserved for this test."""
    return next(_PORTS)

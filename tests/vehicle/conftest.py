"""Vehicle-test setup: the real firmware_sim package (tests/firmware_sim shadows it on sys.path when
tests/ comes first), and a loopback UDP port block of our own (15100-15199)."""

import importlib
import itertools
import os
import sys

import pytest

_ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
if (
    "firmware_sim" not in sys.modules
    or not hasattr(sys.modules["firmware_sim"], "__file__")
    or os.path.dirname(os.path.dirname(sys.modules["firmware_sim"].__file__)) != _ROOT
):
    sys.modules.pop("firmware_sim", None)
    sys.path.insert(0, _ROOT)
    importlib.import_module("firmware_sim")
    sys.path.remove(_ROOT)

_PORTS = itertools.count(15100 + (os.getpid() % 2) * 50, 2)  # two ports per test (multi-vehicle)


@pytest.fixture
def udp_port() -> int:
    """A fresh loopback UDP port (and the one after it) in this engineer's range, for one test."""
    return next(_PORTS)

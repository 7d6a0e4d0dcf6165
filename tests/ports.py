"""Which slice of a fixed loopback port range this test process uses. Test helpers that need blocks of
consecutive ports (a simulator's vehicles count up from a base port) cannot ask the kernel for one;
they split a range into slots instead. The process id spreads concurrent test runs over the slots,
and the pytest-xdist worker number keeps the workers of one run in different slots."""

import os


def process_slot(slots: int) -> int:
    """This process' slot in 0..slots-1: distinct for each xdist worker of one run (as long as there
    are at most `slots` workers), otherwise chosen by process id."""
    worker = os.environ.get("PYTEST_XDIST_WORKER", "")  # gw0, gw1, ... under xdist
    workers = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
    index = int(worker[2:]) if worker.startswith("gw") and worker[2:].isdigit() else 0
    groups = max(1, slots // max(1, workers))
    return ((os.getpid() % groups) * workers + index) % slots


ZENOH_PORTS = range(26000, 29200)
"""Listening ports for Zenoh sessions in tests: below the kernel's ephemeral range, where a port the
kernel handed out as free could be taken again by an outgoing connection (Zenoh's own connects)
before the session binds it."""
_ZENOH_BLOCK = 400
_zenoh_next = [0]


def zenoh_port() -> int:
    """A listening port for a test's Zenoh session: the next of this process' block."""
    base = ZENOH_PORTS.start + _ZENOH_BLOCK * process_slot(len(ZENOH_PORTS) // _ZENOH_BLOCK)
    port = base + _zenoh_next[0] % _ZENOH_BLOCK
    _zenoh_next[0] += 1
    return port

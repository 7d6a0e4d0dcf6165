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

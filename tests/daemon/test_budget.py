"""Memory budget ledger: reservations by name, refusals, scratch, RSS from /proc/self/statm."""

import gc
import mmap
import threading

import numpy as np
import pytest

from coopd.daemon.budget import MIB, BudgetExceeded, MemoryBudget, read_rss


def test_reserve_replace_release():
    b = MemoryBudget(100 * MIB, baseline_bytes=40 * MIB)
    assert b.grid_budget == 60 * MIB
    assert b.reserve("local", 20 * MIB) and b.reserve("global", 30 * MIB)
    assert b.available() == 10 * MIB and b.available("local") == 30 * MIB
    assert not b.reserve("received:5", 11 * MIB)  # would exceed: refused, nothing changed
    assert b.reserved() == 50 * MIB and b.refused == 1
    assert b.reserve("local", 30 * MIB)  # a grown grid replaces its old amount
    assert b.reserved() == 60 * MIB and b.available() == 0
    assert not b.reserve("local", 31 * MIB)
    assert b.release("global") == 30 * MIB and b.release("global") == 0
    assert b.reserve("received:5", 11 * MIB)


def test_scratch_raises_and_releases():
    b = MemoryBudget(64 * MIB, baseline_bytes=0)
    b.reserve("local", 40 * MIB)
    with pytest.raises(BudgetExceeded) as e:
        with b.scratch("merge-scratch", 30 * MIB):
            pass
    assert e.value.available == 24 * MIB and "merge-scratch needs 30.0 MiB" in str(e.value)
    with b.scratch("merge-scratch", 20 * MIB):
        assert b.reserved() == 60 * MIB
    assert b.reserved() == 40 * MIB and b.peak_reserved == 60 * MIB
    with pytest.raises(ValueError):
        b.reserve("x", -1)


def test_snapshot_and_rss():
    b = MemoryBudget.from_mb(4096)
    assert b.baseline_bytes > 10 * MIB  # the interpreter with numpy loaded
    # A fresh anonymous mapping, so no allocator can hand back pages already resident, and no
    # garbage collection in between: a cycle freed from an earlier test would lower RSS meanwhile.
    gc.collect()
    gc.disable()
    try:
        before = read_rss()
        area = mmap.mmap(-1, 64 * MIB)
        block = np.frombuffer(area, np.uint8)
        block[:] = 1  # touched pages count in RSS
        grown = read_rss() - before
    finally:
        gc.enable()
    assert 60 * MIB <= grown <= 70 * MIB
    b.reserve("local", block.nbytes)
    s = b.snapshot()
    assert s["budget_bytes"] == 4096 * MIB and s["entries"] == {"local": 64 * MIB}
    assert s["reserved_bytes"] == 64 * MIB and s["rss_bytes"] >= before + 60 * MIB
    assert s["rss_over_budget"] is False and s["available_bytes"] == b.grid_budget - 64 * MIB
    with open("/proc/self/status") as f:
        vmrss = next(int(line.split()[1]) * 1024 for line in f if line.startswith("VmRSS:"))
    assert abs(vmrss - read_rss()) < 8 * MIB
    del block
    area.close()


def test_concurrent_reservations_never_exceed_the_budget():
    b = MemoryBudget(100, baseline_bytes=0)
    ok = []

    def worker(i):
        for j in range(200):
            if b.reserve(f"t{i}-{j % 5}", 7):
                ok.append(1)
            assert b.reserved() <= 100

    threads = [threading.Thread(target=worker, args=(i,)) for i in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert b.reserved() <= 100 and b.peak_reserved <= 100 and b.refused > 0


def test_budget_below_baseline_fits_nothing():
    b = MemoryBudget(10 * MIB, baseline_bytes=20 * MIB)
    assert b.grid_budget == 0 and not b.reserve("local", 1)

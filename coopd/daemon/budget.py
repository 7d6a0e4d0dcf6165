"""The memory budget: one number (daemon.memory_mb) and a ledger of every grid the daemon holds.

    budget = MemoryBudget.from_mb(512)            # baseline = RSS now (interpreter, numpy, numba)
    budget.reserve("local", grid.size)            # True, or False: over budget (counted)
    with budget.scratch("merge-scratch", n):      # raises BudgetExceeded -> defer the merge
        ...

Grids are accounted by name ("local", "global", "received:5", "merge-scratch", ...); reserving
a name again replaces its amount (a grid that grew). The budget for grids is memory_mb minus the
baseline RSS measured when the ledger is made; the real RSS (/proc/self/statm) is reported next
to the ledger so that `coopctl status` shows both.
"""

import logging
import os
import threading
from contextlib import contextmanager

log = logging.getLogger("coopd.daemon")

MIB = 1 << 20
PAGE_SIZE = os.sysconf("SC_PAGE_SIZE")


class BudgetExceeded(Exception):
    """A reservation that would take the grids past the memory budget."""

    def __init__(self, name: str, requested: int, available: int):
        super().__init__(
            f"{name} needs {requested / MIB:.1f} MiB, only {available / MIB:.1f} MiB of the budget free"
        )
        self.name = name
        self.requested = requested
        self.available = available


def read_rss() -> int:
    """Resident set size of this process in bytes, from /proc/self/statm."""
    with open("/proc/self/statm", "rb") as f:
        return int(f.read().split()[1]) * PAGE_SIZE


class MemoryBudget:
    """Ledger of named byte reservations against one budget; thread-safe."""

    def __init__(self, budget_bytes: int, baseline_bytes: int | None = None):
        if budget_bytes <= 0:
            raise ValueError("budget must be positive")
        self.budget_bytes = int(budget_bytes)
        self.baseline_bytes = int(read_rss() if baseline_bytes is None else baseline_bytes)
        if self.baseline_bytes >= self.budget_bytes:
            log.error(
                "memory budget %.0f MiB is below the baseline RSS %.0f MiB: no grid will fit",
                self.budget_bytes / MIB,
                self.baseline_bytes / MIB,
            )
        self._entries: dict[str, int] = {}
        self._lock = threading.Lock()
        self.refused = 0
        self.peak_reserved = 0
        self.peak_rss = 0

    @classmethod
    def from_mb(cls, memory_mb: int, baseline_bytes: int | None = None) -> "MemoryBudget":
        return cls(memory_mb * MIB, baseline_bytes)

    @property
    def grid_budget(self) -> int:
        """Bytes available to accounted grids: the budget less the baseline RSS."""
        return max(0, self.budget_bytes - self.baseline_bytes)

    def reserved(self) -> int:
        with self._lock:
            return sum(self._entries.values())

    def available(self, name: str | None = None) -> int:
        """Bytes that could still be reserved (for `name`: including what it holds now)."""
        with self._lock:
            held = self._entries.get(name, 0) if name else 0
            return max(0, self.grid_budget - sum(self._entries.values()) + held)

    def reserve(self, name: str, nbytes: int) -> bool:
        """Set `name`'s reservation to nbytes; False (nothing changed) if it would exceed the budget."""
        try:
            self.require(name, nbytes)
        except BudgetExceeded:
            return False
        return True

    def require(self, name: str, nbytes: int) -> None:
        """Like reserve(), but raises BudgetExceeded."""
        nbytes = int(nbytes)
        if nbytes < 0:
            raise ValueError(f"negative reservation for {name}")
        with self._lock:
            others = sum(self._entries.values()) - self._entries.get(name, 0)
            if others + nbytes > self.grid_budget:
                self.refused += 1
                available = max(0, self.grid_budget - others)
                log.warning(
                    "memory budget: refused %s %.1f MiB (%.1f MiB free of %.1f MiB for grids, %d refused)",
                    name,
                    nbytes / MIB,
                    available / MIB,
                    self.grid_budget / MIB,
                    self.refused,
                )
                raise BudgetExceeded(name, nbytes, available)
            self._entries[name] = nbytes
            self.peak_reserved = max(self.peak_reserved, others + nbytes)

    def add(self, name: str, delta: int) -> bool:
        """Grow (delta > 0) or shrink `name`'s reservation by delta bytes; False (nothing changed) if
        growing would pass the budget. For shared running totals (the map server's in-flight
        buffers): counted in `refused` but not logged, as a hostile peer could trigger it at will
        (the sharing component counts and logs its refusals per address)."""
        delta = int(delta)
        with self._lock:
            held = self._entries.get(name, 0)
            total = sum(self._entries.values())
            if delta > 0 and total + delta > self.grid_budget:
                self.refused += 1
                return False
            value = max(0, held + delta)
            if value:
                self._entries[name] = value
            else:
                self._entries.pop(name, None)
            self.peak_reserved = max(self.peak_reserved, total - held + value)
            return True

    def names(self) -> list[str]:
        """The names holding a reservation now."""
        with self._lock:
            return list(self._entries)

    def release(self, name: str) -> int:
        """Drop `name`'s reservation; returns the bytes it held."""
        with self._lock:
            return self._entries.pop(name, 0)

    @contextmanager
    def scratch(self, name: str, nbytes: int):
        """A reservation that lasts for a with-block (merge scratch); raises BudgetExceeded."""
        self.require(name, nbytes)
        try:
            yield
        finally:
            self.release(name)

    def rss(self) -> int:
        value = read_rss()
        self.peak_rss = max(self.peak_rss, value)
        return value

    def snapshot(self) -> dict:
        """Plain data for `coopctl status`."""
        rss = self.rss()
        with self._lock:
            entries = dict(sorted(self._entries.items()))
        reserved = sum(entries.values())
        return {
            "budget_bytes": self.budget_bytes,
            "baseline_bytes": self.baseline_bytes,
            "grid_budget_bytes": self.grid_budget,
            "reserved_bytes": reserved,
            "available_bytes": max(0, self.grid_budget - reserved),
            "peak_reserved_bytes": self.peak_reserved,
            "rss_bytes": rss,
            "peak_rss_bytes": self.peak_rss,
            "rss_over_budget": rss > self.budget_bytes,
            "refused": self.refused,
            "entries": entries,
        }

"""Newest-wins single-slot hand-off between a camera thread and the mapping thread."""

from __future__ import annotations

import threading
from typing import Generic, TypeVar

T = TypeVar("T")


class LatestSlot(Generic[T]):
    """Holds at most one item; a put over an unread item replaces it and counts a drop."""

    def __init__(self):
        self._item: T | None = None
        self._cv = threading.Condition()
        self.puts = 0
        self.dropped = 0

    def put(self, item: T) -> None:
        """Store item, replacing (and counting) any unread one; never blocks beyond the lock."""
        with self._cv:
            if self._item is not None:
                self.dropped += 1
            self._item = item
            self.puts += 1
            self._cv.notify()

    def take(self, timeout: float = 0.0) -> T | None:
        """Remove and return the newest item, waiting up to timeout seconds; None if none came."""
        with self._cv:
            if self._item is None and timeout > 0:
                self._cv.wait_for(lambda: self._item is not None, timeout)
            item, self._item = self._item, None
            return item

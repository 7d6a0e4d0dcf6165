"""The Merger tests' view of the small_house flip maps (the `flip` fixture, conftest.py): a Feed
switchable between the early and later maps, and a Merger over it."""

from types import SimpleNamespace

from coopd.daemon.budget import MemoryBudget
from coopd.daemon.merge_state import MergerSettings, MergeSources
from coopd.daemon.merger import Merger
from coopd.sharing.wire import MapMeta, encode_map


class Feed:
    """What the Merger reads: our local map and the one received map, switchable between stages."""

    def __init__(self, maps, stage="early"):
        self.maps, self.stage, self.version = maps, stage, 1

    def set(self, stage):
        self.stage, self.version = stage, self.version + 1

    def local(self):
        return self.maps[self.stage][0].copy(), self.version

    def received(self):
        grid = self.maps[self.stage][1]
        return [SimpleNamespace(vehicle_id=2, version=self.version,
                                data=encode_map(grid, MapMeta(2, self.version)))]


def flip_merger(feed, merge_fn, sources: dict | None = None, **settings) -> Merger:
    """Vehicle 1's Merger over feed (and further `sources`), not distributed unless `settings` say
    so, never merging on its own period."""
    return Merger(1, MergerSettings(**{"period_s": 3600, "distributed": False, **settings}),
                  MergeSources(feed.local, feed.received, **(sources or {})),
                  MemoryBudget(256 << 20, baseline_bytes=0), merge_fn=merge_fn)

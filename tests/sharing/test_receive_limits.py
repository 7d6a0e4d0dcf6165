"""The receive path against hostile senders: decompression bombs are refused before they are
decoded, decodes are charged to the memory budget one at a time, nothing refused is stored."""

import threading

import pytest
from hostile_maps import bomb
from sharing_support import failures, settings, wait_until

from coopd.daemon.budget import MIB, MemoryBudget
from coopd.grid import OccupancyGrid
from coopd.sharing import mtp, wire
from coopd.sharing.service import (
    DECODE_BYTES_PER_CELL,
    DECODE_LEDGER,
    SharingConfig,
    SharingService,
    wire_verifier,
)
from coopd.sharing.transport import PeerLink

BS = 4096


class LedgerSpy(MemoryBudget):
    """A memory budget that remembers the largest amount each name ever held."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.peaks: dict[str, int] = {}

    def add(self, name, delta):
        ok = super().add(name, delta)
        with self._lock:
            self.peaks[name] = max(self.peaks.get(name, 0), self._entries.get(name, 0))
        return ok


def real_service(budget, cap_cells: int, decoded: list, **transport) -> SharingService:
    """A server with the real wire format, a memory budget and a merge cap (like the daemon's)."""
    s = settings(block_size=BS, max_cells=400_000_000, max_bytes=64 << 20, **transport)
    verify = wire_verifier(s.max_cells, s.max_bytes)

    def counting_verify(message):
        decoded.append(len(message))
        verify(message)

    cfg = SharingConfig(vehicle_id=1, listen_host="127.0.0.1", port=0, transport=s)
    return SharingService(cfg, verify=counting_verify, budget=budget, cell_cap=lambda: cap_cells).start()


def send(svc, message, vid: int = 5, source: str | None = None) -> int:
    link = PeerLink.connect(*svc.address, svc.config.transport, vid, source=source)
    try:
        return link.send_map(message)[0]
    finally:
        link.close()


def small_map(vid: int, version: int, side: int = 64) -> bytes:
    grid = OccupancyGrid.empty((side, side, 8), 0.1)
    grid.flat[::7] = 100
    return wire.encode_map(grid, wire.MapMeta(vid, version, 1.0))


def test_a_decompression_bomb_is_refused_before_it_is_decoded_and_never_stored():
    budget = LedgerSpy(64 * MIB, baseline_bytes=0)
    decoded: list = []
    cap = budget.grid_budget // 12  # what the daemon's merger could merge: 5.6 M cells
    svc = real_service(budget, cap, decoded)
    try:
        message = bomb(5, 1)  # 104 bytes announcing 100 M cells
        assert len(message) < 1000 and wire.peek(message).cells == 100_000_000
        assert send(svc, message) == mtp.ACK_REJECTED
        assert wait_until(lambda: failures(svc) == {"oversize": 1}, 3), failures(svc)
        assert decoded == [] and svc.received.all() == []
        assert budget.peaks.get(DECODE_LEDGER, 0) == 0
        assert send(svc, small_map(5, 2)) == mtp.ACK_OK  # the same peer's real map still gets in
        assert svc.received.version(5) == 2 and len(decoded) == 1
    finally:
        svc.stop()


def test_concurrent_maps_decode_one_at_a_time_within_the_budget():
    budget = LedgerSpy(256 * MIB, baseline_bytes=0)
    decoded: list = []
    svc = real_service(budget, 50_000_000, decoded)
    cells = 512 * 512 * 8
    results = []
    try:
        def one(vid):
            results.append(send(svc, small_map(vid, 1, side=512), vid, source=f"127.0.0.{vid}"))

        threads = [threading.Thread(target=one, args=(10 + k,)) for k in range(8)]
        for t in threads:
            t.start()
        for t in threads:
            t.join(30)
        assert results == [mtp.ACK_OK] * 8 and len(decoded) == 8
        assert budget.peaks[DECODE_LEDGER] == DECODE_BYTES_PER_CELL * cells  # never two at once
        assert budget.snapshot()["entries"].get(DECODE_LEDGER) is None  # all given back
    finally:
        svc.stop()


def test_a_decode_that_does_not_fit_the_budget_is_refused_and_counted():
    budget = LedgerSpy(8 * MIB, baseline_bytes=0)
    decoded: list = []
    svc = real_service(budget, 50_000_000, decoded)
    try:
        assert send(svc, small_map(5, 1, side=1024)) == mtp.ACK_REJECTED  # 8 M cells: 24 MiB to decode
        assert wait_until(lambda: failures(svc) == {"memory": 1}, 3), failures(svc)
        assert decoded == [] and svc.received.all() == []
    finally:
        svc.stop()


@pytest.mark.parametrize("cells_ok", [True, False])
def test_a_checkpointed_map_too_large_to_merge_is_set_aside_at_load(tmp_path, cells_ok):
    from coopd.daemon.checkpoint import CheckpointStore

    store = CheckpointStore(tmp_path)
    assert store.save_message("peer-9", bomb(9, 3)) is not None
    cp = store.load_latest("peer-9", max_cells=200_000_000 if cells_ok else 5_000_000)
    if cells_ok:
        assert cp is not None and cp.grid.size == 100_000_000
    else:
        assert cp is None and store.set_aside == 1 and store.generations("peer-9") == []
        assert "more than the 5000000" in store.problems[-1]

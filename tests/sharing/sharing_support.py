"""Helpers for the sharing tests: services on loopback with the test message format."""

import socket
import time

import numpy as np
import sharing_testmsg as tm

from coopd.grid import OccupancyGrid
from coopd.sharing import versions, wire
from coopd.sharing.service import SharingConfig, SharingService
from coopd.sharing.transport import TransportSettings
from coopd.sharing.wire import MapMeta

FAST = dict(connect_timeout=0.3, read_timeout=1.0, handshake_timeout=1.0, idle_timeout=10.0,
            transfer_base_s=3.0, block_size=256, max_bytes=4 << 20, max_inflight_bytes=16 << 20,
            max_cells=1 << 20)


def settings(**overrides) -> TransportSettings:
    return TransportSettings(**{**FAST, **overrides})


def service(vid: int, host: str = "127.0.0.1", port: int = 0, peers=(), peer_ports=(), relay=False,
            scan_period=0.2, grace_period=30.0, max_epoch_ahead_s=versions.MAX_EPOCH_AHEAD_S,
            on_own_refused=None, **transport) -> SharingService:
    cfg = SharingConfig(vehicle_id=vid, listen_host=host, port=port, peers=tuple(peers),
                        peer_ports=tuple(peer_ports), scan_period=scan_period, grace_period=grace_period,
                        relay=relay, max_epoch_ahead_s=max_epoch_ahead_s, transport=settings(**transport))
    return SharingService(cfg, inspect=tm.inspect, on_own_refused=on_own_refused)


def wait_until(pred, timeout: float = 10.0, step: float = 0.05) -> bool:
    """Poll `pred` until true or `timeout` seconds passed (bounded)."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if pred():
            return True
        time.sleep(step)
    return bool(pred())


def free_port(host: str = "127.0.0.1") -> int:
    with socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET) as s:
        s.bind((host, 0))
        return s.getsockname()[1]


def failures(svc: SharingService) -> dict:
    """All failure counts of a service, summed over peers and unidentified addresses, by cause."""
    out: dict = {}
    snap = svc.peers.snapshot()
    for p in snap["peers"]:
        for k, v in p["failures"].items():
            out[k] = out.get(k, 0) + v
    for counts in snap["unidentified_failures"].values():
        for k, v in counts.items():
            out[k] = out.get(k, 0) + v
    return out


def growing_maps(versions: int, seed: int = 0):
    """(grid, version, message) of a map explored room by room: each version knows a new patch and
    changes a few cells seen before, and the box grows now and then."""
    rng = np.random.default_rng(seed)
    grid = OccupancyGrid.empty((60, 60, 20), 0.1)
    grid.cells[10:50, 10:50, 4:16] = rng.choice(np.array([0, 0, 100, 20], dtype=np.int8), size=(40, 40, 12))
    out = []
    for v in range(1, versions + 1):
        x, y = rng.integers(-20 - v, 20 + v, size=2)
        patch = rng.choice(np.array([0, 0, 0, 100, 30], dtype=np.int8), size=(6, 6, 8))
        keys = np.stack(np.meshgrid(np.arange(x, x + 6), np.arange(y, y + 6), np.arange(-4, 4),
                                    indexing="ij"), axis=-1).reshape(-1, 3)
        grid.set_keys(keys, patch.reshape(-1))
        known = np.argwhere(grid.cells != -1)
        if len(known):
            pick = known[rng.integers(0, len(known), size=10)]
            grid.cells[pick[:, 0], pick[:, 1], pick[:, 2]] = 70
        snap = grid.shrunk(pad=4)
        out.append((snap, v, wire.encode_map(snap, MapMeta(1, v, 100.0 + v))))
    return out

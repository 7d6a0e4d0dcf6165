"""Helpers for the sharing tests: services on loopback with the test message format."""

import socket
import time

import sharing_testmsg as tm

from coopd.sharing import versions
from coopd.sharing.service import SharingConfig, SharingService
from coopd.sharing.transport import TransportSettings

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

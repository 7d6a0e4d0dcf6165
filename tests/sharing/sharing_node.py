"""A sharing endpoint in its own process, driven over stdin/stdout by the multi-host tests.

Commands (one per line): 'publish VERSION SIZE' (a deterministic test map of SIZE payload bytes),
'status' (prints one JSON line), 'quit'. Prints 'ready HOST PORT' once listening.
"""

import argparse
import hashlib
import json
import logging
import sys

import sharing_testmsg as tm

from coopd.sharing.service import SharingConfig, SharingService
from coopd.sharing.transport import TransportSettings
from coopd.sharing.zenoh_link import ZenohSettings


def real_map(vid: int, version: int, size: int) -> bytes:
    """A real coopd map message (wire.encode_map) of a deterministic grid with about `size` cells."""
    import numpy as np

    from coopd.grid import OccupancyGrid
    from coopd.sharing import wire

    side = max(4, round((size / 20) ** 0.5))
    rng = np.random.default_rng(vid * 1000 + version)
    cells = rng.choice(np.array([-1, -1, -1, 0, 0, 40, 100], dtype=np.int8), (side, side, 20))
    return wire.encode_map(OccupancyGrid(cells, 0.1, (-side // 2, -side // 2, 0)),
                           wire.MapMeta(vid, version, float(version)))


def payload(vid: int, version: int, size: int) -> bytes:
    seed = hashlib.sha256(f"{vid}/{version}".encode()).digest()
    return (seed * (size // len(seed) + 1))[:size]


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--vid", type=int, required=True)
    ap.add_argument("--host", required=True)
    ap.add_argument("--port", type=int, required=True)
    ap.add_argument("--peers", required=True)
    ap.add_argument("--key", default="")
    ap.add_argument("--rate", type=float, default=0.0, help="max send rate, bytes/s")
    ap.add_argument("--relay", action="store_true")
    ap.add_argument("--grace", type=float, default=30.0)
    ap.add_argument("--max-inflight-mb", type=int, default=512)
    ap.add_argument("--real", action="store_true", help="real wire map messages (inspect + full decode)")
    ap.add_argument("--max-connections", type=int, default=32)
    ap.add_argument("--zenoh-mode", default="", help="also share over Zenoh in this mode (peer, router)")
    ap.add_argument("--zenoh-listen", action="append", default=[], help="Zenoh endpoint to listen on")
    ap.add_argument("--zenoh-connect", action="append", default=[], help="Zenoh endpoint to connect to")
    ap.add_argument("--no-mtp", action="store_true", help="Zenoh only")
    a = ap.parse_args()
    logging.basicConfig(level=logging.INFO, stream=sys.stderr,
                        format=f"%(asctime)s node{a.vid} %(name)s %(levelname)s %(message)s")
    settings = TransportSettings(connect_timeout=0.3, read_timeout=1.0, handshake_timeout=1.0,
                                 idle_timeout=20.0, transfer_base_s=20.0, max_bytes=64 << 20,
                                 max_cells=64 << 20, swarm_key=a.key.encode() or None, max_send_rate=a.rate,
                                 max_inflight_bytes=a.max_inflight_mb << 20,
                                 max_connections=a.max_connections,
                                 max_connections_per_address=a.max_connections)
    cfg = SharingConfig(vehicle_id=a.vid, listen_host=a.host, port=a.port, peers=(a.peers,),
                        peer_ports=(a.port,), scan_period=0.3, grace_period=a.grace, relay=a.relay,
                        transport=settings, mtp=not a.no_mtp,
                        zenoh=None if not a.zenoh_mode else ZenohSettings(
                            swarm="test", mode=a.zenoh_mode, listen=tuple(a.zenoh_listen),
                            connect=tuple(a.zenoh_connect), multicast_scouting=False))
    if a.real:
        from coopd.sharing.service import wire_inspect, wire_verifier

        svc = SharingService(cfg, inspect=wire_inspect,
                             verify=wire_verifier(settings.max_cells, settings.max_bytes)).start()
    else:
        svc = SharingService(cfg, inspect=tm.inspect).start()
    print("ready", *(svc.address or ("zenoh", 0)), flush=True)
    for line in sys.stdin:
        cmd = line.split()
        if not cmd:
            continue
        if cmd[0] == "publish":
            version, size = int(cmd[1]), int(cmd[2])
            message = (real_map(a.vid, version, size) if a.real
                       else tm.make(a.vid, version, payload(a.vid, version, size)))
            svc.publish(message, version)
            print("ok", flush=True)
        elif cmd[0] == "status":
            st = svc.stats()
            st["received"] = {str(m.vehicle_id): [m.version, len(m.data), hashlib.sha256(m.data).hexdigest()]
                              for m in svc.received.all()}
            print(json.dumps(st, default=str), flush=True)
        elif cmd[0] == "rss":  # peak and current resident memory, kB (for the memory-bound tests)
            fields = dict(line.split(":", 1) for line in open("/proc/self/status") if ":" in line)
            print(json.dumps({k: int(fields[k].split()[0]) for k in ("VmHWM", "VmRSS")}), flush=True)
        elif cmd[0] == "quit":
            break
    svc.stop()


if __name__ == "__main__":
    main()

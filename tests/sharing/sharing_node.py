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
    a = ap.parse_args()
    logging.basicConfig(level=logging.INFO, stream=sys.stderr,
                        format=f"%(asctime)s node{a.vid} %(name)s %(levelname)s %(message)s")
    settings = TransportSettings(connect_timeout=0.3, read_timeout=1.0, handshake_timeout=1.0,
                                 idle_timeout=20.0, transfer_base_s=20.0, max_bytes=64 << 20,
                                 max_cells=64 << 20, swarm_key=a.key.encode() or None, max_send_rate=a.rate)
    cfg = SharingConfig(vehicle_id=a.vid, listen_host=a.host, port=a.port, peers=(a.peers,),
                        peer_ports=(a.port,), scan_period=0.3, grace_period=a.grace, relay=a.relay,
                        transport=settings)
    svc = SharingService(cfg, inspect=tm.inspect).start()
    print("ready", *svc.address, flush=True)
    for line in sys.stdin:
        cmd = line.split()
        if not cmd:
            continue
        if cmd[0] == "publish":
            version, size = int(cmd[1]), int(cmd[2])
            svc.publish(tm.make(a.vid, version, payload(a.vid, version, size)), version)
            print("ok", flush=True)
        elif cmd[0] == "status":
            st = svc.stats()
            st["received"] = {str(m.vehicle_id): [m.version, len(m.data), hashlib.sha256(m.data).hexdigest()]
                              for m in svc.received.all()}
            print(json.dumps(st, default=str), flush=True)
        elif cmd[0] == "quit":
            break
    svc.stop()


if __name__ == "__main__":
    main()

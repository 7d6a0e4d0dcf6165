"""Probe the FC link (and optionally a camera socket) from a shell: one JSON status line per second.

python -m coopd.vehicle udpin:0.0.0.0:14540 [--camera /run/cam.sock] [--seconds 10] [--signing-key-file F]
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time

from .link import LinkConfig, VehicleLink
from .signing import read_signing_key


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m coopd.vehicle", description=__doc__.splitlines()[0])
    p.add_argument("connection", help="MAVLink connection string: udpin:HOST:PORT, udpout:HOST:PORT, "
                   "tcp:HOST:PORT, tcpin:HOST:PORT, /dev/DEVICE[,BAUD] or a MAVSDK URL (docs/vehicle.md)")
    p.add_argument("--camera", default=None, help="camera socket (path or tcp:HOST:PORT) to associate frames")
    p.add_argument("--seconds", type=float, default=10.0, help="how long to probe (default 10 s)")
    p.add_argument("--signing-key-file", default=None, help="MAVLink 2 signing key file (64 hex characters)")
    a = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s %(message)s")
    try:
        key = None if a.signing_key_file is None else read_signing_key(a.signing_key_file)
        link = VehicleLink(LinkConfig(connection=a.connection, signing_key=key))
    except (OSError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    source = assoc = None
    if a.camera:
        from ..camera import SocketDepthSource, SocketSourceConfig
        from ..mapping.association import FrameAssociator

        source = SocketDepthSource(SocketSourceConfig(a.camera), fc=link, host_to_fc=link.fc_time_at)
        assoc = FrameAssociator(link)
        source.start()
    link.start()
    end = time.monotonic() + max(0.0, a.seconds)
    next_print = time.monotonic() + 1.0
    try:
        while time.monotonic() < end:
            if source is not None:
                frame = source.slot.take(timeout=0.05)
                if frame is not None:
                    assoc.associate(frame)
            else:
                time.sleep(0.05)
            if time.monotonic() >= next_print:
                next_print += 1.0
                out = {"vehicle": link.status()}
                if source is not None:
                    out["camera"] = source.status()
                    out["association"] = assoc.status()
                print(json.dumps(out), flush=True)
    except KeyboardInterrupt:
        pass
    finally:
        link.stop()
        if source is not None:
            source.stop()
    return 0 if link.status()["link"] == "ok" else 1


if __name__ == "__main__":
    sys.exit(main())

"""Stand-in for the `coopd` executable, used only by the systemd-nspawn boot test.

coopd/daemon/main.py (the real wiring of vehicle, camera, mapping, sharing and merging) is not
written yet; this process runs the real service pieces around an idle map so that the unit
file, sd_notify, the watchdog, the control socket and checkpoints can be shown working under a
real systemd: config -> checkpoint resume -> control socket -> READY=1 -> watchdog pings while
the main loop beats -> checkpoint + exit on SIGTERM. The extra control command `hang` stops the
main loop's heartbeat (as a deadlocked stage would), so the watchdog restart can be observed.
"""

import argparse
import logging
import os
import signal
import sys
import threading
import time

from coopd.daemon.budget import MemoryBudget
from coopd.daemon.checkpoint import CheckpointStore
from coopd.daemon.config import load_config
from coopd.daemon.control import ControlServer
from coopd.daemon.notify import Notifier, WatchdogPinger
from coopd.daemon.threads import ThreadPriorities
from coopd.grid import OccupancyGrid
from coopd.sharing.wire import MapMeta, encode_map

log = logging.getLogger("coopd.daemon")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="coopd-standin")
    parser.add_argument("--config", default="/etc/coopd/coopd.toml")
    args = parser.parse_args(argv)
    config = load_config(args.config)
    logging.basicConfig(
        level=config.daemon.log_level.upper(), stream=sys.stderr, format="%(name)s: %(message)s"
    )
    started = time.monotonic()
    notifier = Notifier()
    budget = MemoryBudget.from_mb(config.daemon.memory_mb)
    priorities = ThreadPriorities()
    store = CheckpointStore(config.daemon.state_dir, keep=config.daemon.checkpoint_keep)
    cp = store.load_latest("local")
    grid = cp.grid if cp else OccupancyGrid.empty((40, 40, 20), config.mapping.resolution)
    version = cp.meta.version if cp else 0
    budget.reserve("local", grid.size)
    encode_map(grid, MapMeta(config.vehicle.id))  # compile/load the encoder now, not during SIGTERM
    beat = {"t": time.monotonic(), "hung": False, "restarts_seen": os.environ.get("COOPD_RESTARTS", "")}
    stop = threading.Event()

    def status(_args):
        counts = grid.counts()
        return {
            "vehicle_id": config.vehicle.id,
            "pid": os.getpid(),
            "state": "running",
            "uptime_s": time.monotonic() - started,
            "map": {
                "shape": list(grid.shape),
                "cells": grid.size,
                "known": counts.known,
                "resolution_m": grid.resolution,
                "version": version,
            },
            "memory": budget.snapshot(),
            "threads": priorities.report(),
            "control": server.stats(),
            "checkpoint": store.stats(),
            "resumed_from": str(cp.path) if cp else None,
        }

    def hang(_args):
        beat["hung"] = True
        return {"hung": True}

    server = ControlServer(
        config.daemon.control_socket,
        {"status": status, "hang": hang},
        max_clients=config.daemon.control_max_clients,
        timeout_s=config.daemon.control_timeout_s,
    )
    server.on_thread_start = lambda: priorities.apply("control")
    server.start()
    pinger = WatchdogPinger(notifier, healthy=lambda: time.monotonic() - beat["t"] < 2.0).start()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    priorities.apply("mapping")
    notifier.ready(f"map {grid.size} cells, version {version}")
    log.info(
        "ready: pid %d, map version %d, resumed from %s", os.getpid(), version, cp.path if cp else "nothing"
    )
    while not stop.wait(0.2):
        if not beat["hung"]:
            beat["t"] = time.monotonic()
    t0 = time.monotonic()
    notifier.stopping("checkpointing")
    store.save("local", grid, MapMeta(config.vehicle.id, version + 1, time.time()))
    pinger.stop()
    server.stop()
    log.info("stopped in %.2f s", time.monotonic() - t0)
    return 0


if __name__ == "__main__":
    code = main()
    # Everything is saved and closed: skip the interpreter's final garbage collection, which takes
    # seconds once numba/llvmlite are loaded (measured 2-3 s), so systemctl stop returns promptly.
    logging.shutdown()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)

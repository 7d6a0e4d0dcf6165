"""coopd: the cooperative mapping daemon (`coopd --config /etc/coopd/coopd.toml`).

Logs go to stderr; under systemd each line carries its syslog priority for journald
(coopd.daemon.logs). Exit codes: 0 stopped by SIGTERM/SIGINT (final
checkpoint written), 1 could not start (control socket in use, port taken, pyrealsense2 missing),
2 bad command line or configuration (the message names the key).
"""

import argparse
import faulthandler
import logging
import os
import signal
import sys

from coopd.daemon.config import DEFAULT_CONFIG_PATH, ConfigError, as_dict, from_dict, load_config
from coopd.daemon.logs import setup_logging
from coopd.version import add_version_option

log = logging.getLogger("coopd.daemon")

EXIT_OK, EXIT_START_FAILED, EXIT_CONFIG = 0, 1, 2

OVERRIDES = (
    # (option, dest, type, config section, key, help)
    ("--vehicle-id", "vehicle_id", int, "vehicle", "id", "MAVLink system id / swarm id"),
    ("--mavlink", "mavlink", str, "vehicle", "mavlink", "flight-controller connection string"),
    ("--camera", "camera", str, "camera", "source", "depth source (socket:/PATH, tcp:HOST:PORT, realsense)"),
    ("--sharing-port", "sharing_port", int, "sharing", "port", "TCP port of the map server"),
    ("--listen-host", "listen_host", str, "sharing", "listen_host", "address the map server listens on"),
    ("--state-dir", "state_dir", str, "daemon", "state_dir", "checkpoint directory"),
    ("--control-socket", "control_socket", str, "daemon", "control_socket", "coopctl's unix socket"),
    ("--memory-mb", "memory_mb", int, "daemon", "memory_mb", "memory budget of the process, MiB"),
    ("--checkpoint-period", "checkpoint_period_s", float, "daemon", "checkpoint_period_s",
     "seconds between checkpoints (0: only on stop)"),
    ("--log-level", "log_level", str, "daemon", "log_level", "debug, info, warning or error"),
    ("--swarm-key-file", "swarm_key_file", str, "sharing", "swarm_key_file", "the swarm key file"),
)


def parse_args(argv) -> argparse.Namespace:
    p = argparse.ArgumentParser(
        prog="coopd", description="Cooperative 3D occupancy mapping daemon.",
        epilog=f"exit codes: {EXIT_OK} stopped by SIGTERM/SIGINT (final checkpoint written), "
               f"{EXIT_START_FAILED} could not start, {EXIT_CONFIG} bad command line or configuration",
    )
    add_version_option(p)
    p.add_argument("--config", default=str(DEFAULT_CONFIG_PATH), help=f"TOML file ({DEFAULT_CONFIG_PATH})")
    p.add_argument("--no-config", action="store_true", help="start from the built-in defaults, no file")
    for option, dest, kind, section, key, text in OVERRIDES:
        p.add_argument(option, dest=dest, type=kind, default=None, help=f"{text} (overrides {section}.{key})")
    p.add_argument("--peer", dest="peers", action="append", default=None, metavar="HOST[:PORT]",
                   help="peer to scan, repeatable (replaces sharing.peers)")
    p.add_argument("--no-sharing", action="store_true", help="sharing.enabled = false")
    p.add_argument("--open", action="store_true",
                   help="sharing.open = true: no swarm key, accept maps from any host (thesis interop)")
    p.add_argument("--no-distributed", action="store_true",
                   help="merging.distributed = false (neither publish nor use peers' merge results)")
    p.add_argument("--check-config", action="store_true", help="validate the configuration and exit")
    return p.parse_args(argv)


def build_config(args: argparse.Namespace):
    """The file's configuration with the command-line overrides applied (validated as one)."""
    table = as_dict(from_dict({}) if args.no_config else load_config(args.config))
    for _, dest, _, section, key, _ in OVERRIDES:
        value = getattr(args, dest)
        if value is not None:
            table[section][key] = value
    if args.peers is not None:
        table["sharing"]["peers"] = args.peers
    if args.no_sharing:
        table["sharing"]["enabled"] = False
    if args.open:
        table["sharing"]["open"] = True
    if args.no_distributed:
        table["merging"]["distributed"] = False
    return from_dict(table)


def main(argv=None, fast_exit: bool = True) -> int:
    """Entry point of the coopd script; returns the exit code."""
    args = parse_args(argv)
    try:
        config = build_config(args)
    except (ConfigError, OSError) as e:
        print(f"coopd: configuration: {e}", file=sys.stderr)
        return EXIT_CONFIG
    if args.check_config:
        if config.vehicle.signing_key_file:  # read at start too: a key that fails here would stop it
            from coopd.vehicle.signing import read_signing_key

            try:
                read_signing_key(config.vehicle.signing_key_file)
            except (OSError, ValueError) as e:
                print(f"coopd: configuration: vehicle.signing_key_file: {e}", file=sys.stderr)
                return EXIT_CONFIG
        print(f"coopd: configuration OK (vehicle {config.vehicle.id})")
        return EXIT_OK
    setup_logging(config.daemon.log_level)

    from coopd.daemon.service import Daemon, StartupError, install_signal_handlers

    try:
        daemon = Daemon(config)
    except (OSError, ValueError, RuntimeError) as e:
        log.error("cannot start: %s", e)
        return EXIT_START_FAILED
    install_signal_handlers(daemon)
    faulthandler.register(signal.SIGUSR1, all_threads=True)  # operators: kill -USR1 dumps every stack
    try:
        daemon.start()
    except (StartupError, OSError) as e:
        log.error("cannot start: %s", e)
        daemon.request_stop("start failed")
        daemon.shutdown()
        return EXIT_START_FAILED
    daemon.run()
    daemon.shutdown()
    if fast_exit:
        # Everything the daemon owns is stopped and the checkpoint is on disk; the interpreter's own
        # teardown (numba/LLVM finalizers) would add about a second to every systemctl stop.
        logging.shutdown()
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(EXIT_OK)
    return EXIT_OK


if __name__ == "__main__":
    sys.exit(main())

"""Load (or, on an empty numba cache, compile) every kernel the daemon needs before READY=1.

The daemon runs this at each start; scripts/install runs it once as `python -m coopd.daemon.warmup`
with the unit's NUMBA_CACHE_DIR, as the unit's user, so that the first `systemctl start coopd`
loads compiled kernels from the cache instead of spending most of a minute in the JIT.
"""

import argparse
import logging
import sys
import time
from collections.abc import Callable

from coopd.daemon.config import DEFAULT_CONFIG_PATH, Config, ConfigError, load_config
from coopd.grid import OccupancyGrid
from coopd.mapping import MapperConfig, load_kernels
from coopd.sharing.wire import MapMeta, decode_map, encode_map

log = logging.getLogger(__name__)


def warm_up_kernels(mapping: MapperConfig, vehicle_id: int, merge_fn: Callable | None) -> str | None:
    """Run the mapping, codec and (when merge_fn is given) merging kernels once on small inputs.
    Returns why the warm-up merge failed (merging stays on; the daemon reports it), else None."""
    grid = decode_map(encode_map(load_kernels(mapping), MapMeta(vehicle_id, 1)))[0]
    grid.counts()
    if merge_fn is None:
        return None
    room = OccupancyGrid.empty((40, 40, 12), mapping.resolution)
    room.cells[5:35, 5:35, 2] = 0
    room.cells[5:35, (5, 34), 2:10] = 90
    room.cells[(5, 34), 5:35, 2:10] = 90
    try:
        merge_fn(room, [room.copy()], None)
    except Exception as e:  # merging stays on: the failure shows in status and in each merge
        problem = f"warm-up merge failed: {type(e).__name__}: {e}"
        log.error("merging: %s", problem, exc_info=True)
        return problem
    return None


def main(argv=None) -> int:
    """`python -m coopd.daemon.warmup [--config PATH]`: fill NUMBA_CACHE_DIR (install time)."""
    ap = argparse.ArgumentParser(prog="python -m coopd.daemon.warmup", description=main.__doc__)
    ap.add_argument("--config", default=DEFAULT_CONFIG_PATH,
                    help="the daemon's configuration (its [mapping] table); absent file: the defaults")
    args = ap.parse_args(argv)
    try:
        config = load_config(args.config)
    except FileNotFoundError:
        config = Config()
    except (ConfigError, OSError) as e:
        print(f"coopd warm-up: configuration: {e}", file=sys.stderr)
        return 1
    from coopd.daemon.merger import find_merge_all

    t0 = time.monotonic()
    merge_fn, problem = find_merge_all()
    problem = problem or warm_up_kernels(config.mapping, config.vehicle.id, merge_fn)
    if problem:
        print(f"coopd warm-up: merging: {problem}", file=sys.stderr)
        return 1
    print(f"coopd warm-up: kernels compiled and cached in {time.monotonic() - t0:.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())

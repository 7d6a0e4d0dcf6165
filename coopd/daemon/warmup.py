"""Load (or, on an empty numba cache, compile) every kernel the daemon needs before READY=1.

The daemon runs this at each start; scripts/install runs it once as `python -m coopd.daemon.warmup`
with the unit's NUMBA_CACHE_DIR, as the unit's user, so that the first `systemctl start coopd`
loads compiled kernels from the cache instead of spending most of a minute in the JIT (and at
install time also those of a real merge, which the daemon would otherwise compile at its first).
"""

import argparse
import logging
import sys
import time
from collections.abc import Callable

import numpy as np

from coopd.daemon.config import DEFAULT_CONFIG_PATH, Config, ConfigError, load_config
from coopd.geometry import rigid, rotation_z
from coopd.grid import OccupancyGrid, transform_grid
from coopd.grid.sectors import sector_distances_of
from coopd.mapping import MapperConfig, load_kernels
from coopd.sharing.wire import MapMeta, decode_map, encode_map

log = logging.getLogger(__name__)


def furnished_room(resolution: float) -> OccupancyGrid:
    """An 8 x 7 x 1.4 m room (at 0.1 m) with an inner wall, a door and furniture: enough structure
    for a merge of it with a turned copy to run the whole search, refinement and validation."""
    g = OccupancyGrid.empty((80, 70, 14), resolution)
    c = g.cells
    c[4:76, 4:66, 1:13] = 0
    c[4:76, 4:66, (1, 12)] = 90
    c[4:76, (4, 65), 1:13] = 90
    c[(4, 75), 4:66, 1:13] = 90
    c[30, 4:40, 1:13] = 90
    c[30, 20:24, 2:10] = 0
    furniture = ((10, 10, 6, 3, 5), (50, 12, 3, 8, 9), (60, 50, 5, 5, 3), (15, 50, 9, 2, 7),
                 (40, 45, 2, 2, 12))  # cells: corner x, y, extent x, y, height
    for x, y, w, d, h in furniture:
        c[x:x + w, y:y + d, 2:2 + h] = 90
    return g


def warm_up_kernels(mapping: MapperConfig, vehicle_id: int, merge_fn: Callable | None,
                    full_merge: bool = False) -> str | None:
    """Run the mapping, codec and (when merge_fn is given) merging kernels once on small inputs.
    full_merge: also merge a furnished room with a turned copy (the kernels of a real merge's search,
    refinement and validation; tens of seconds on an empty cache, so at install time only).
    Returns why a warm-up merge failed (merging stays on; the daemon reports it), else None."""
    grid = decode_map(encode_map(load_kernels(mapping), MapMeta(vehicle_id, 1)))[0]
    grid.counts()
    sector_distances_of(np.zeros((5, 5, 2), np.int8), (0, 0), mapping.resolution, (0.0, 0.0), 0.0,
                        0.05, 0.3, 50)
    if merge_fn is None:
        return None
    room = OccupancyGrid.empty((40, 40, 12), mapping.resolution)
    room.cells[5:35, 5:35, 2] = 0
    room.cells[5:35, (5, 34), 2:10] = 90
    room.cells[(5, 34), 5:35, 2:10] = 90
    pairs = [(room, room.copy())]
    if full_merge:
        furnished = furnished_room(mapping.resolution)
        turned = rigid(rotation_z(np.radians(30.0)), np.array([0.4, -0.3, 0.0]))
        pairs.append((furnished, transform_grid(furnished, turned)))
    try:
        for a, b in pairs:
            merge_fn(a, [b], None)
        vouched_merge(merge_fn, room)
    except Exception as e:  # merging stays on: the failure shows in status and in each merge
        problem = f"warm-up merge failed: {type(e).__name__}: {e}"
        log.error("merging: %s", problem, exc_info=True)
        return problem
    return None


def vouched_merge(merge_fn: Callable, room: OccupancyGrid) -> None:
    """The merge a drone runs on a peer's merge result: maps placed by vouched edges, one direct and
    one through another map, checked and fused (kernels a search does not call in these forms)."""
    from coopd.merging.hints import Hint  # only with merge_fn: the build has coopd.merging

    shifted = rigid(np.eye(3), np.array([4 * room.resolution, 0.0, 0.0]))
    inverse = rigid(np.eye(3), -shifted[:3, 3])
    moved = transform_grid(room, inverse)  # the room seen from 4 cells further along x
    hints = [[Hint(shifted, "peer", vouched=True)], [Hint(np.eye(4), "peer", via=0, vouched=True)]]
    merge_fn(room, [moved, moved.copy()], None, hints=hints)


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
    problem = problem or warm_up_kernels(config.mapping, config.vehicle.id, merge_fn, full_merge=True)
    if problem:
        print(f"coopd warm-up: merging: {problem}", file=sys.stderr)
        return 1
    print(f"coopd warm-up: kernels compiled and cached in {time.monotonic() - t0:.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())

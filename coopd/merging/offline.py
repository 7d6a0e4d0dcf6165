"""Offline merging of map files, the logic behind `coopctl map merge A.cmap B.cmap [...] -o out.cmap --json`.

The first file is the reference. A map's frame is the one its grid carries (key (0, 0, 0) centred on
the recorded origin; for thesis type-0 files, which record none, the loader centres it on cell
(0, 0, 0)), so transforms map points of each file's frame into the first file's frame, in metres.
"""

import time
from collections.abc import Callable
from pathlib import Path

from ..grid import OccupancyGrid
from .multi import merge_all
from .params import MergeParams, coopd_params


def merge_grids(grids: list[OccupancyGrid], params: MergeParams | None = None) -> tuple[OccupancyGrid, dict]:
    """(global map, JSON-ready report) for already-loaded grids; the first is the reference."""
    if len(grids) < 2:
        raise ValueError("merging needs at least two maps")
    t0 = time.perf_counter()
    res = merge_all(grids[0], list(grids[1:]), params or coopd_params())
    maps = []
    for r in res.results:
        maps.append({"accepted": bool(r.accepted),
                     "transform": [[float(v) for v in row] for row in r.transform] if r.accepted else None,
                     "inliers": int(r.inliers), "score": round(float(r.score), 4),
                     "seconds": round(float(r.timings.get("total", sum(r.timings.values()))), 4),
                     "reason": r.reason})
    return res.global_map, {"reference": 0, "maps": maps, "rounds": res.rounds,
                            "seconds": round(time.perf_counter() - t0, 4)}


def merge_files(paths: list[str | Path], out_path: str | Path | None,
                load: Callable[[Path], OccupancyGrid], save: Callable[[OccupancyGrid, Path], None],
                params: MergeParams | None = None) -> dict:
    """Load the files, merge them into the first one's frame, save the global map; returns the report
    whose "maps" list names, for every input after the first, accepted, transform (4x4 row-major,
    metres, that map's frame -> the first map's frame), inliers, score and seconds."""
    grids = [load(Path(p)) for p in paths]
    merged, report = merge_grids(grids, params)
    for entry, p in zip(report["maps"], paths[1:], strict=True):
        entry["path"] = str(p)
    report["inputs"] = [str(p) for p in paths]
    if out_path is not None:
        save(merged, Path(out_path))
        report["output"] = str(out_path)
    return report

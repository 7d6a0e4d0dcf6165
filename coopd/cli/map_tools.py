"""`coopctl map info|convert`: offline tools on map files; no daemon needed."""

from pathlib import Path

from coopd.sharing.wire_options import ENCODINGS, DecodeLimits

from .output import NOT_MERGED, OK, USAGE, CommandError, about_file, add_json_option, emit

# Map decoding and exports (numpy, numba kernels) load inside the handlers, as in daemon_commands:
# building coopctl's parser for status, peers or merge-now must not import them.

FORMATS = ("ply", "png", "bt", "cmap")


def register(subparsers) -> None:
    """Add the `map` command group to coopctl."""
    p = subparsers.add_parser("map", help="inspect and convert map files (.cmap)")
    sub = p.add_subparsers(dest="map_command", metavar="SUBCOMMAND", required=True)

    info = sub.add_parser("info", help="size, resolution, origin, cell counts, compression ratio")
    info.add_argument("file", type=Path,
                      help="a .cmap file (coopd or thesis map message), or an OctoMap .bt / .ot file")
    add_json_option(info)
    _limit_args(info)
    info.set_defaults(handler=run_info)

    conv = sub.add_parser("convert", help="export to PLY, PNG, OctoMap .bt, or (re-)encode as .cmap")
    conv.add_argument("file", type=Path, help="a .cmap file, or an OctoMap .bt / .ot file")
    conv.add_argument("--to", required=True, choices=FORMATS, help="output format")
    conv.add_argument("--z", type=float, default=None, metavar="METRES",
                      help="png only: horizontal slice at this height (map frame) instead of the top view")
    conv.add_argument("-o", "--output", type=Path, default=None, help="output path (default: next to FILE)")
    conv.add_argument("--encoding", default="default", choices=["default", *ENCODINGS],
                      help="cmap only: payload encoding of the written message")
    add_json_option(conv)
    _limit_args(conv)
    conv.set_defaults(handler=run_convert)

    merge = sub.add_parser("merge", help="merge maps into the first one's frame (no GPS, no initial guess); "
                                         f"exit {NOT_MERGED.code} when a map could not be merged")
    merge.add_argument("files", type=Path, nargs="+",
                       help="two or more map files (.cmap, OctoMap .bt / .ot); the first is the reference")
    merge.add_argument("-o", "--output", type=Path, required=True, help="the merged global map (.cmap)")
    add_json_option(merge, "print the report as JSON: per input after the first, accepted, transform "
                           "(4x4 row-major, metres, into the first map's frame), inliers, score, seconds")
    merge.add_argument("--variant", default="coopd", choices=["coopd", "thesis", "rigid", "features"],
                       help="pipeline variant (default coopd; thesis = the thesis' own pipeline)")
    _limit_args(merge)
    merge.set_defaults(handler=run_merge)


def _limit_args(p) -> None:
    p.add_argument("--max-cells", type=int, default=DecodeLimits.max_cells, help="refuse larger maps")
    p.add_argument("--max-bytes", type=int, default=DecodeLimits.max_bytes, help="refuse larger files")


def _limits(args) -> DecodeLimits:
    return DecodeLimits(max_cells=args.max_cells, max_bytes=args.max_bytes)


def map_info(path: Path, limits: DecodeLimits) -> dict:
    """Everything `map info` reports about a map file, as plain data (the message fields are None
    for an OctoMap file, which has no message header)."""
    from coopd.io.bt import is_octomap, parse_header, read_octomap
    from coopd.io.cmap import read_cmap_bytes
    from coopd.sharing.wire import decode_map, peek

    data = read_cmap_bytes(path, limits)
    with about_file(path):
        if is_octomap(data):
            octo = parse_header(data)
            grid = read_octomap(data, limits.max_cells)
            source = {"format": f"octomap {'.bt' if octo.binary else '.ot'} ({octo.tree_type})",
                      "message_type": None, "format_version": None, "encoding": None, "vehicle_id": None,
                      "map_version": None, "stamp": None}
        else:
            header = peek(data)
            grid, meta = decode_map(data, limits)
            source = {"format": "cmap", "message_type": header.message_type,
                      "format_version": header.format_version, "encoding": header.encoding,
                      "vehicle_id": meta.vehicle_id, "map_version": meta.version, "stamp": meta.stamp}
    counts = grid.counts()
    lo, hi = grid.bounds_m()
    return {
        "file": str(path),
        "file_bytes": len(data),
        **source,
        "shape": list(grid.shape),
        "cells": grid.size,
        "resolution_m": grid.resolution,
        "origin_cells": [int(v) for v in grid.offset],
        "origin_m": [float(v) * grid.resolution for v in grid.offset],
        "extent_m": {"min": [float(v) for v in lo], "max": [float(v) for v in hi]},
        "known": counts.known,
        "occupied": counts.occupied,
        "free": counts.free,
        "inaccessible": counts.inaccessible,
        "unknown": counts.unknown,
        "compression_ratio": grid.size / len(data),
    }


def run_info(args) -> int:
    info = map_info(args.file, _limits(args))
    known_pct = 100.0 * info["known"] / info["cells"]
    message = [
        f"message         type {info['message_type']} format {info['format_version']}, "
        f"encoding {info['encoding']}",
        f"vehicle         {info['vehicle_id']}, map version {info['map_version']}, stamp {info['stamp']}",
    ] if info["format"] == "cmap" else [f"format          {info['format']}"]
    lines = [
        f"file            {info['file']} ({info['file_bytes']} bytes)",
        *message,
        f"size            {' x '.join(map(str, info['shape']))} = {info['cells']} cells",
        f"resolution      {info['resolution_m']} m",
        f"origin          cell {tuple(info['origin_cells'])} at "
        f"({', '.join(f'{v:.3f}' for v in info['origin_m'])}) m",
        f"extent          ({', '.join(f'{v:.2f}' for v in info['extent_m']['min'])}) .. "
        f"({', '.join(f'{v:.2f}' for v in info['extent_m']['max'])}) m",
        f"known cells     {info['known']} ({known_pct:.2f} %): occupied {info['occupied']}, "
        f"free {info['free']}, inaccessible {info['inaccessible']}",
        f"compression     {info['compression_ratio']:.1f} : 1 (cells / file bytes)",
    ]
    emit(args, info, "\n".join(lines))
    return OK.code


def default_output(path: Path, fmt: str, z: float | None) -> Path:
    if fmt == "png":
        return path.with_name(f"{path.stem}_{'top' if z is None else f'z{z:g}m'}.png")
    if fmt == "cmap":
        return path.with_name(f"{path.stem}.converted.cmap")
    return path.with_suffix(f".{fmt}")


def check_z(fmt: str, z: float | None) -> None:
    """--z (a slice height) means something for png output only."""
    if z is not None and fmt != "png":
        raise CommandError("--z applies to png output only", USAGE)


def write_map(grid, out: Path, fmt: str, z: float | None, cmap_bytes, meta=None) -> dict:
    """Write `grid` to `out` as `fmt`; returns what was written (for the text line and --json).
    `cmap_bytes()` gives the message a .cmap holds (the daemon's exact bytes, or a re-encoding);
    `meta` (the map's MapMeta) titles a top view with the vehicle and the map's time."""
    from coopd.io import export_bt, export_ply, export_png_slice, export_png_top
    from coopd.io.atomic import write_atomic
    from coopd.io.maps import FOREIGN_VEHICLE_ID
    from coopd.io.png import map_title

    written = {"file": str(out), "format": fmt}
    if fmt == "cmap":
        data = cmap_bytes()
        write_atomic(out, data)
        return {**written, "bytes": len(data)}
    if fmt == "ply":
        return {**written, "points": export_ply(grid, out)}
    if fmt == "png" and z is None:
        vehicle = None if meta is None or meta.vehicle_id == FOREIGN_VEHICLE_ID else meta.vehicle_id
        title = map_title(grid.resolution, vehicle, meta.stamp if meta is not None else None)
        export_png_top(grid, out, title=title)
        return {**written, "view": "top", "title": title}
    if fmt == "png":
        export_png_slice(grid, out, z)
        return {**written, "view": "slice", "z_m": z}
    return {**written, "bytes": export_bt(grid, out)}


def written_text(written: dict) -> str:
    """`wrote FILE (what)` for write_map's answer."""
    if "points" in written:
        what = f"{written['points']} occupied points"
    elif written.get("view") == "top":
        what = "top view"
    elif "view" in written:
        what = f"slice at z = {written['z_m']} m"
    else:
        what = f"{written['bytes']} bytes"
    return f"wrote {written['file']} ({what})"


def run_convert(args) -> int:
    from coopd.io import load_map
    from coopd.sharing.wire import encode_map

    check_z(args.to, args.z)
    grid, meta = load_map(args.file, _limits(args))
    out = args.output or default_output(args.file, args.to, args.z)
    written = write_map(grid, out, args.to, args.z, lambda: encode_map(grid, meta, args.encoding), meta)
    emit(args, {"source": str(args.file), **written}, written_text(written))
    return OK.code


def run_merge(args) -> int:
    """`coopctl map merge`: merge_all over the files, the global map saved, a report printed."""
    from coopd.io import load_map, save_cmap
    from coopd.merging import VARIANTS, merge_files
    from coopd.sharing.wire import MapMeta

    if len(args.files) < 2:
        raise ValueError("map merge needs at least two map files")
    limits = _limits(args)
    first_meta = load_map(args.files[0], limits)[1]

    def save(grid, path):
        save_cmap(path, grid, MapMeta(first_meta.vehicle_id, first_meta.version, first_meta.stamp))

    report = merge_files(args.files, args.output, lambda path: load_map(path, limits)[0], save,
                         VARIANTS[args.variant]())
    lines = []
    for entry in report["maps"]:
        verdict = "merged" if entry["accepted"] else f"not merged ({entry['reason']})"
        lines.append(f"{entry['path']}: {verdict}, score {entry['score']}, {entry['inliers']} inliers, "
                     f"{entry['seconds']} s")
    emit(args, report, "\n".join([*lines, f"wrote {args.output}"]))
    return OK.code if all(e["accepted"] for e in report["maps"]) else NOT_MERGED.code

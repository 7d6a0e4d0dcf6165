"""`coopctl status|peers|merge-now|dump-map`: talk to a running coopd over its control socket.

The daemon supplies plain data (see docs/operations.md, "Control protocol"); coopctl formats it.
dump-map: the daemon streams the map's serialized message (the .cmap bytes) back over the socket
and coopctl writes or converts it on its side, so the daemon never writes into the operator's
directories and needs no write access outside its StateDirectory.
"""

import os
from pathlib import Path

from coopd.daemon import control
from coopd.daemon.control import DEFAULT_CONTROL_SOCKET
from coopd.sharing.wire_options import DecodeLimits

from .map_tools import FORMATS, check_z, write_map, written_text
from .output import DEFERRED, FAILED, OK, USAGE, CommandError, add_json_option, emit

# Map decoding and exports (numpy, numba kernels) load only when dump-map runs: status, peers and
# merge-now start fast and need no numba cache directory.

SOCKET_ENV = "COOPD_SOCKET"
MERGE_EXIT = {"done": OK, "queued": OK, "failed": FAILED, "deferred": DEFERRED}


def register(subparsers) -> None:
    """Add status, peers, merge-now and dump-map to coopctl."""
    status = subparsers.add_parser("status", help="state of the running daemon")
    add_json_option(status, "print the daemon's status as one JSON object")
    status.add_argument("--sections", default=None, metavar="NAME,...",
                        help="only these sections of the status (e.g. peers,merges: a monitor polling many "
                             "drones); the others print as '-'")
    _socket_args(status)
    status.set_defaults(handler=run_status)

    peers = subparsers.add_parser("peers", help="peer vehicles the daemon knows")
    add_json_option(peers)
    _socket_args(peers)
    peers.set_defaults(handler=run_peers)

    merge = subparsers.add_parser(
        "merge-now", help=f"merge the maps now (exit {OK.code} done/queued, {FAILED.code} failed, "
                          f"{DEFERRED.code} deferred)"
    )
    add_json_option(merge)
    _socket_args(merge, timeout=120.0)
    merge.set_defaults(handler=run_merge_now)

    dump = subparsers.add_parser(
        "dump-map", help="save the local, global or a peer's map (.cmap, PLY, PNG, .bt)"
    )
    dump.add_argument(
        "map",
        nargs="?",
        default="local",
        help="local (default), global, or a peer's vehicle id (e.g. 3 or peer:3)",
    )
    dump.add_argument("-o", "--output", type=Path, required=True, help="file to write")
    dump.add_argument(
        "--to",
        choices=FORMATS,
        default=None,
        help="output format (default: from the file suffix: .cmap, .ply, .png or .bt)",
    )
    dump.add_argument(
        "--z",
        type=float,
        default=None,
        metavar="METRES",
        help="png only: horizontal slice at this height instead of the top view",
    )
    dump.add_argument("--max-bytes", type=int, default=DecodeLimits.max_bytes, help="refuse larger maps")
    dump.add_argument("--max-cells", type=int, default=DecodeLimits.max_cells, help="refuse larger maps")
    add_json_option(dump)
    _socket_args(dump, timeout=60.0)
    dump.set_defaults(handler=run_dump_map)


def _socket_args(p, timeout: float = 10.0) -> None:
    p.add_argument(
        "--socket",
        default=os.environ.get(SOCKET_ENV, DEFAULT_CONTROL_SOCKET),
        help=f"control socket (default: ${SOCKET_ENV} or {DEFAULT_CONTROL_SOCKET})",
    )
    p.add_argument(
        "--timeout", type=float, default=timeout, help=f"seconds to wait for the answer ({timeout:g})"
    )


def _call(args, cmd: str, cmd_args: dict | None = None, max_blob_bytes: int = 0):
    """One request to the daemon; ControlError (an OSError) carries the operator's message."""
    return control.request(args.socket, cmd, cmd_args, timeout_s=args.timeout, max_blob_bytes=max_blob_bytes)


# ------------------------------------------------------------------------------------------ status
def run_status(args) -> int:
    sections = None if args.sections is None else [n for n in args.sections.split(",") if n]
    result, _ = _call(args, "status", None if sections is None else {"sections": sections})
    emit(args, result, format_status(result))
    return OK.code


def format_status(s: dict) -> str:
    """The human table of `coopctl status`; missing parts print as '-'."""
    rows = [
        (
            "coopd",
            f"vehicle {s.get('vehicle_id', '-')}, {s.get('state', '-')}, up {_duration(s.get('uptime_s'))}"
            f" (pid {s.get('pid', '-')})",
        )
    ]
    link = s.get("link") or {}
    rows.append(
        (
            "link",
            f"{link.get('state', '-')}"
            + (f": {link['reason_detail']}" if link.get("reason_detail") else "")
            + (f", last message {_num(link.get('age_s'), 2)} s ago" if link.get("age_s") is not None else ""),
        )
    )
    pose = s.get("pose")
    if pose:
        x, y, z = (pose.get("position_m") or [None] * 3)[:3]
        rows.append(
            (
                "pose",
                f"x {_num(x, 2)}  y {_num(y, 2)}  z {_num(z, 2)} m, yaw {_num(pose.get('yaw_deg'), 1)} deg"
                f" ({_num(pose.get('age_s'), 2)} s old)",
            )
        )
    else:
        rows.append(("pose", "-"))
    m = s.get("map") or {}
    if m:
        shape = " x ".join(str(v) for v in m.get("shape", [])) or "-"
        cells, known = m.get("cells"), m.get("known")
        pct = f" ({100.0 * known / cells:.1f} %)" if cells and known is not None else ""
        rows.append(
            (
                "map",
                f"{shape} = {cells} cells at {m.get('resolution_m', '-')} m, {known} known{pct}, "
                f"version {m.get('version', '-')}",
            )
        )
    else:
        rows.append(("map", "-"))
    f = s.get("frames") or {}
    rows.append(
        (
            "frames",
            f"{f.get('in', '-')} in, {f.get('dropped', '-')} dropped, {f.get('rejected', '-')} rejected",
        )
    )
    peers = s.get("peers")
    if isinstance(peers, list):
        rows.append(
            ("peers", f"{len(peers)}" + (": " + ", ".join(_peer_short(p) for p in peers) if peers else ""))
        )
    else:
        rows.append(("peers", "-"))
    receiving = (s.get("sharing") or {}).get("receiving") or []
    if receiving:
        rows.append(("receiving", ", ".join(_transfer_short(r) for r in receiving)))
    mg = s.get("merges") or {}
    rows.append(
        (
            "merges",
            f"{mg.get('done', '-')} done, {mg.get('failed', '-')} failed, {mg.get('deferred', '-')} deferred",
        )
    )
    if "full_registrations" in mg:
        rows.append(
            (
                "merge work",
                f"{mg['full_registrations']} full registrations, {mg.get('hinted', '-')} hinted "
                f"({mg.get('hinted_peer', '-')} by peers' results), {mg.get('hint_rejected', '-')} hints "
                f"refused, {mg.get('rechecks', 0)} rechecks, {mg.get('cpu_s', '-')} s CPU"
                + ("" if mg.get("distributed", True) else ", not distributed"),
            )
        )
    if mg.get("start_error"):
        rows.append(("merging", f"{mg.get('state', '-')}" if not mg.get("available", True)
                     else f"{mg.get('state', '-')}; {mg['start_error']}"))
    ob = s.get("obstacles") or {}
    if ob and not ob.get("sending"):
        rows.append(("obstacles", f"not sending; FC: {ob.get('fc', '-')}"))
    elif ob:
        nearest = ob.get("nearest_m")
        why = "always" if ob.get("enabled") else f"FC asks: {ob.get('fc', '-')}"
        rows.append(("obstacles", f"{ob.get('sent', '-')} OBSTACLE_DISTANCE sent at "
                     f"{ob.get('rate_hz', '-')} Hz ({why}); "
                     f"last: nearest {'-' if nearest is None else f'{nearest} m'}, "
                     f"{ob.get('sectors_no_data', '-')} sectors no data, {ob.get('sectors_free', '-')} free; "
                     f"{ob.get('no_pose', '-')} without a pose"))
    vw = s.get("viewer") or {}
    if vw.get("enabled"):
        rows.append(("viewer", f"{vw.get('url') or 'not served'} at {vw.get('rate_hz', '-')} Hz; "
                     f"{vw.get('bricks', '-')} bricks shown, {vw.get('bricks_sent', '-')} sent, "
                     f"{vw.get('bricks_deleted', '-')} deleted, {vw.get('errors', '-')} errors"))
        rec = vw.get("recording")
        if rec:
            rows.append(("recording", f"{rec['path']}, {_mib(rec['bytes'])}"
                         + ("" if rec["open"] else f", stopped: {rec['stopped'] or 'closed'}")))
    stalled = (s.get("watchdog") or {}).get("stalled_threads") or {}
    if stalled:
        rows.append(("health", "not healthy (watchdog not fed): "
                     + "; ".join(f"{k} {v}" for k, v in sorted(stalled.items()))))
    if mg.get("provisional"):
        rows.append(("provisional", "merges found, held out of the global map until confirmed: "
                     + ", ".join(f"vehicle {v}" for v in mg["provisional"])))
    if mg.get("contested"):
        rows.append(("contested", "maps that fit ours two ways, left out: "
                     + ", ".join(f"vehicle {v}" for v in mg["contested"])))
    mem = s.get("memory") or {}
    if mem:
        entries = ", ".join(f"{k} {_mib(v)}" for k, v in (mem.get("entries") or {}).items())
        rows.append(
            (
                "memory",
                f"RSS {_mib(mem.get('rss_bytes'))} of {_mib(mem.get('budget_bytes'))} budget"
                + (f" (OVER BUDGET for {mem.get('over_budget_for_s')} s)" if mem.get("over_budget") else "")
                + "; "
                f"grids {_mib(mem.get('reserved_bytes'))} reserved"
                + (f" ({entries})" if entries else "")
                + (f"; {mem['refused']} reservations refused" if mem.get("refused") else ""),
            )
        )
    threads = s.get("threads") or []
    for i, t in enumerate(threads):
        mark = (
            ""
            if t.get("applied") == t.get("requested")
            else f" (asked {t.get('requested')}: {t.get('note', '')})"
        )
        rows.append(
            (
                "threads" if i == 0 else "",
                f"{t.get('role', '?'):<9} tid {t.get('tid', '-')}, nice {t.get('applied', '-')}{mark}",
            )
        )
    c = s.get("control") or {}
    if c:
        rows.append(
            (
                "control",
                f"{c.get('served', 0)} served, {c.get('bad_requests', 0)} bad, "
                f"{c.get('oversize', 0)} oversize, {c.get('timeouts', 0)} timed out, "
                f"{c.get('evicted', 0)} evicted; replies: {c.get('reply_timeouts', 0)} cut at their "
                f"deadline, {c.get('evicted_replies', 0)} cut for room, {c.get('refused_busy', 0)} busy, "
                f"{c.get('reply_buffer_bytes', 0)} of {c.get('reply_buffer_limit', 0)} B queued",
            )
        )
    cp = s.get("checkpoint") or {}
    if cp:
        rows.append(
            (
                "checkpoint",
                f"{cp.get('saved', 0)} saved, {cp.get('failed', 0)} failed, "
                f"{cp.get('set_aside', 0)} set aside; last {cp.get('last_path') or '-'}",
            )
        )
    width = max(len(k) for k, _ in rows) + 2
    return "\n".join(f"{k:<{width}}{v}" for k, v in rows)


def _peer_short(p: dict) -> str:
    return f"{p.get('vehicle_id', '?')} (v{p.get('map_version', '-')}, {_num(p.get('last_seen_s'), 1)} s ago)"


def _transfer_short(r: dict) -> str:
    who = "unidentified peer" if r.get("vehicle_id") is None else f"vehicle {r['vehicle_id']}"
    return f"map from {who} at {r.get('address', '?')}: {_mib(r.get('received_bytes'))} of " \
           f"{_mib(r.get('announced_bytes'))}"


def _num(v, digits: int) -> str:
    return "-" if not isinstance(v, (int, float)) else f"{v:.{digits}f}"


def _mib(v) -> str:
    if not isinstance(v, (int, float)):
        return "-"
    return f"{v / 2**20:.1f} MiB" if abs(v) >= 2**20 or v == 0 else f"{v / 1024:.1f} KiB"


def _duration(s) -> str:
    if not isinstance(s, (int, float)):
        return "-"
    s = int(s)
    d, rest = divmod(s, 86400)
    h, rest = divmod(rest, 3600)
    m, sec = divmod(rest, 60)
    return (f"{d} d " if d else "") + (f"{h} h " if d or h else "") + f"{m} min {sec} s"


# ------------------------------------------------------------------------------------- peers, merge
def run_peers(args) -> int:
    result, _ = _call(args, "peers")
    emit(args, result, format_peers(result.get("peers") or []))
    return OK.code


def format_peers(peers: list) -> str:
    """The table of `coopctl peers`."""
    if not peers:
        return "no peers"
    lines = [
        f"{'vehicle':>7}  {'address':<22} {'link':<6} {'map version':>11} {'map bytes':>10} {'last seen':>9}"
    ]
    for p in peers:
        lines.append(
            f"{p.get('vehicle_id', '?'):>7}  {str(p.get('address', '-')):<22} "
            f"{'up' if p.get('connected') else 'down':<6} {p.get('map_version', '-'):>11} "
            f"{p.get('map_bytes', '-'):>10} {_num(p.get('last_seen_s'), 1):>7} s"
        )
    return "\n".join(lines)


def run_merge_now(args) -> int:
    result, _ = _call(args, "merge-now")
    outcome = str(result.get("outcome", "done"))
    emit(args, result, f"merge-now: {outcome}" + (f": {result['detail']}" if result.get("detail") else ""))
    return MERGE_EXIT.get(outcome, FAILED).code


# ---------------------------------------------------------------------------------------- dump-map
def map_request(which: str) -> dict:
    """The dump-map request arguments for 'local', 'global', '3' or 'peer:3'."""
    if which in ("local", "global"):
        return {"map": which}
    ident = which.removeprefix("peer:")
    if not ident.isdigit():
        raise CommandError(f"map must be local, global or a peer's vehicle id, not {which!r}", USAGE)
    return {"map": "peer", "vehicle_id": int(ident)}


def output_format(path: Path, to: str | None) -> str:
    """--to, or the format the file's suffix names; an unknown suffix without --to is an error."""
    if to:
        return to
    suffix = path.suffix.lower().lstrip(".")
    if suffix not in FORMATS:
        raise CommandError(f"{path}: cannot tell the output format from the suffix {path.suffix!r}: "
                           f"name the file .{', .'.join(FORMATS)} or give --to", USAGE)
    return suffix


def run_dump_map(args) -> int:
    from coopd.sharing.wire import decode_map

    fmt = output_format(args.output, args.to)
    check_z(fmt, args.z)
    limits = DecodeLimits(max_cells=args.max_cells, max_bytes=args.max_bytes)
    result, blob = _call(args, "dump-map", map_request(args.map), max_blob_bytes=limits.max_bytes)
    if blob is None:
        raise ValueError("the daemon sent no map")
    grid, meta = decode_map(blob, limits)  # validates (CRC, size) before anything is written
    written = write_map(grid, args.output, fmt, args.z, lambda: blob, meta)
    counts = grid.counts()
    dumped = {**written, "map": result.get("map", args.map), "vehicle_id": meta.vehicle_id,
              "map_version": meta.version, "shape": list(grid.shape), "known": counts.known}
    shape = " x ".join(map(str, grid.shape))
    emit(args, dumped, f"{written_text(written)}: {dumped['map']} map of vehicle {meta.vehicle_id}, "
                       f"version {meta.version}, {shape} cells, {counts.known} known")
    return OK.code

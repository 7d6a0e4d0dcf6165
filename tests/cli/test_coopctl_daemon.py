"""coopctl status/peers/merge-now/dump-map against a control server with fake handlers."""

import json
import os
import shutil
import socket
import sys
import tempfile

import numpy as np
import pytest
from PIL import Image

from coopd.cli.coopctl import main
from coopd.daemon.control import BlobReply, CommandFailed, ControlServer
from coopd.grid import OccupancyGrid
from coopd.io import load_cmap
from coopd.sharing.wire import MapMeta, encode_map


def _grid(seed: int) -> OccupancyGrid:
    rng = np.random.default_rng(seed)
    cells = rng.choice(np.array([-1, -1, 0, 10, 80, -2], np.int8), size=(20, 16, 8)).astype(np.int8)
    return OccupancyGrid(cells, 0.1, (-10, -8, 0))


STATUS = {
    "vehicle_id": 3,
    "pid": 4242,
    "state": "running",
    "uptime_s": 3725.0,
    "link": {"state": "ok", "age_s": 0.02},
    "pose": {"position_m": [1.2, -3.4, 2.0], "yaw_deg": 90.0, "age_s": 0.03},
    "map": {"shape": [20, 16, 8], "cells": 2560, "known": 1900, "resolution_m": 0.1, "version": 41},
    "frames": {"in": 1234, "dropped": 12, "rejected": 3},
    "peers": [
        {
            "vehicle_id": 5,
            "address": "10.42.0.5:7400",
            "connected": True,
            "map_version": 7,
            "map_bytes": 5120,
            "last_seen_s": 1.5,
        }
    ],
    "sharing": {"receiving": [{"vehicle_id": 5, "address": "10.42.0.5", "received_bytes": 40960,
                               "announced_bytes": 3 << 20}]},
    "merges": {"done": 10, "failed": 1, "deferred": 2, "full_registrations": 3, "hinted": 7, "hinted_own": 5,
               "hinted_peer": 2, "hint_rejected": 1, "rechecks": 2, "cpu_s": 4.25, "distributed": True,
               "contested": [5], "provisional": [4, 6]},
    "memory": {
        "budget_bytes": 512 << 20,
        "rss_bytes": 200 << 20,
        "reserved_bytes": 3 << 20,
        "entries": {"local": 1 << 20, "global": 2 << 20},
        "refused": 2,
    },
    "threads": [
        {"role": "mavlink", "tid": 11, "requested": -5, "applied": 0, "note": "EPERM"},
        {"role": "merging", "tid": 12, "requested": 10, "applied": 10, "note": ""},
    ],
    "control": {"served": 5, "bad_requests": 1, "oversize": 0, "timeouts": 0, "evicted": 0},
    "checkpoint": {
        "saved": 4,
        "failed": 0,
        "set_aside": 1,
        "last_path": "/var/lib/coopd/local.0000000004.cmap",
    },
}
MAPS = {
    "local": (_grid(1), MapMeta(3, 41, 100.0)),
    "global": (_grid(2), MapMeta(3, 9, 101.0)),
    5: (_grid(3), MapMeta(5, 7, 99.0)),
}


def _dump(args):
    key = args.get("vehicle_id") if args.get("map") == "peer" else args.get("map")
    if key not in MAPS:
        raise CommandFailed(f"no map {args}")
    grid, meta = MAPS[key]
    return BlobReply({"map": str(args.get("map"))}, encode_map(grid, meta))


MERGE_OUTCOME = {"outcome": "deferred", "detail": "needs 40 MiB, 12 MiB free in the budget"}
HANDLERS = {
    "status": lambda a: {k: v for k, v in STATUS.items()
                         if "sections" not in a or k in a["sections"] or k in ("vehicle_id", "state")},
    "peers": lambda a: {"peers": STATUS["peers"]},
    "merge-now": lambda a: MERGE_OUTCOME,
    "dump-map": _dump,
}


@pytest.fixture
def daemon():
    d = tempfile.mkdtemp(prefix="coopd-cli-", dir="/tmp")
    os.chmod(d, 0o755)
    path = os.path.join(d, "control.sock")
    srv = ControlServer(path, HANDLERS).start()
    yield path
    srv.stop()
    shutil.rmtree(d, ignore_errors=True)


def test_status_table_and_json(daemon, capsys):
    assert main(["status", "--socket", daemon]) == 0
    out = capsys.readouterr().out
    assert "vehicle 3, running, up 1 h 2 min 5 s (pid 4242)" in out
    assert "x 1.20  y -3.40  z 2.00 m, yaw 90.0 deg" in out
    assert "20 x 16 x 8 = 2560 cells at 0.1 m, 1900 known (74.2 %), version 41" in out
    assert "1234 in, 12 dropped, 3 rejected" in out
    assert "10 done, 1 failed, 2 deferred" in out
    assert "receiving    map from vehicle 5 at 10.42.0.5: 40.0 KiB of 3.0 MiB\n" in out
    assert "3 full registrations, 7 hinted (2 by peers' results), 1 hints refused, 2 rechecks, " \
        "4.25 s CPU\n" in out
    assert "provisional  merges found, held out of the global map until confirmed: vehicle 4, " \
        "vehicle 6\n" in out
    assert "contested    maps that fit ours two ways, left out: vehicle 5\n" in out
    assert "RSS 200.0 MiB of 512.0 MiB budget" in out and "2 reservations refused" in out
    assert "nice 0 (asked -5: EPERM)" in out and "nice 10\n" in out
    assert main(["status", "--json", "--socket", daemon]) == 0
    assert json.loads(capsys.readouterr().out) == STATUS


def test_status_sections_ask_the_daemon_for_part_of_it(daemon, capsys):
    assert main(["status", "--json", "--sections", "peers,merges", "--socket", daemon]) == 0
    assert set(json.loads(capsys.readouterr().out)) == {"vehicle_id", "state", "peers", "merges"}
    assert main(["status", "--sections", "merges", "--socket", daemon]) == 0
    out = capsys.readouterr().out
    assert "10 done, 1 failed, 2 deferred" in out and "\nmap          -\n" in out, out


def test_status_socket_from_environment(daemon, capsys, monkeypatch):
    monkeypatch.setenv("COOPD_SOCKET", daemon)
    assert main(["status", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["vehicle_id"] == 3


def test_peers_and_merge_now(daemon, capsys):
    assert main(["peers", "--socket", daemon]) == 0
    out = capsys.readouterr().out
    assert "10.42.0.5:7400" in out and "up" in out
    assert main(["peers", "--json", "--socket", daemon]) == 0
    assert json.loads(capsys.readouterr().out)["peers"][0]["vehicle_id"] == 5
    assert main(["merge-now", "--socket", daemon]) == 4  # deferred
    assert "merge-now: deferred: needs 40 MiB" in capsys.readouterr().out
    MERGE_OUTCOME["outcome"] = "done"
    try:
        assert main(["merge-now", "--json", "--socket", daemon]) == 0
        assert json.loads(capsys.readouterr().out)["outcome"] == "done"
    finally:
        MERGE_OUTCOME["outcome"] = "deferred"


@pytest.mark.parametrize("which,key", [("local", "local"), ("global", "global"), ("5", 5), ("peer:5", 5)])
def test_dump_map_cmap_is_the_exact_message(daemon, tmp_path, capsys, which, key):
    out = tmp_path / "m.cmap"
    assert main(["dump-map", which, "-o", str(out), "--socket", daemon]) == 0
    grid, meta = load_cmap(out)
    assert grid.same_cells(MAPS[key][0]) and meta == MAPS[key][1]
    assert out.read_bytes() == encode_map(*MAPS[key])
    assert f"vehicle {meta.vehicle_id}, version {meta.version}" in capsys.readouterr().out


def test_dump_map_exports(daemon, tmp_path, capsys):
    grid = MAPS["global"][0]
    assert main(["dump-map", "global", "-o", str(tmp_path / "g.ply"), "--socket", daemon]) == 0
    ply = (tmp_path / "g.ply").read_bytes()
    assert ply.startswith(b"ply") and f"element vertex {grid.counts().occupied}".encode() in ply
    assert main(["dump-map", "global", "-o", str(tmp_path / "g.png"), "--socket", daemon]) == 0
    assert Image.open(tmp_path / "g.png").size[0] > 0
    vehicle = MAPS["global"][1].vehicle_id
    assert Image.open(tmp_path / "g.png").info["Title"].startswith(f"coopd map of vehicle {vehicle}, ")
    assert main(["dump-map", "global", "-o", str(tmp_path / "s.png"), "--z", "0.3", "--socket", daemon]) == 0
    assert Image.open(tmp_path / "s.png").size[0] > 0
    assert main(["dump-map", "global", "-o", str(tmp_path / "g.bt"), "--socket", daemon]) == 0
    assert (tmp_path / "g.bt").read_bytes().startswith(b"# Octomap OcTree binary file")
    assert main(["dump-map", "local", "-o", str(tmp_path / "x.out"), "--to", "cmap", "--socket", daemon]) == 0
    assert load_cmap(tmp_path / "x.out")[0].same_cells(MAPS["local"][0])
    capsys.readouterr()


def test_dump_map_errors(daemon, tmp_path, capsys):
    assert main(["dump-map", "7", "-o", str(tmp_path / "x.cmap"), "--socket", daemon]) == 1
    assert "no map" in capsys.readouterr().err
    assert main(["dump-map", "somebody", "-o", str(tmp_path / "x.cmap"), "--socket", daemon]) == 2
    assert "vehicle id" in capsys.readouterr().err
    assert (
        main(["dump-map", "local", "-o", str(tmp_path / "x.cmap"), "--max-bytes", "100", "--socket", daemon])
        == 1
    )
    assert "limit of 100" in capsys.readouterr().err
    assert (
        main(["dump-map", "local", "-o", str(tmp_path / "x.cmap"), "--max-cells", "100", "--socket", daemon])
        == 1
    )
    assert "exceeds the limit of 100" in capsys.readouterr().err
    assert not (tmp_path / "x.cmap").exists()


def test_daemon_not_running(tmp_path, capsys):
    path = tmp_path / "absent.sock"
    assert main(["status", "--socket", str(path)]) == 5
    err = capsys.readouterr().err
    assert "coopd is not running" in err and "systemctl start coopd" in err


def test_not_running_message_from_the_program(tmp_path):
    """Run as `python -m coopd.cli.coopctl`: one line on stderr, exit code 5 (unreachable), no traceback."""
    import subprocess

    root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    r = subprocess.run(
        [sys.executable, "-m", "coopd.cli.coopctl", "status", "--socket", str(tmp_path / "x.sock")],
        capture_output=True,
        text=True,
        cwd=root,
        timeout=120,
    )
    assert r.returncode == 5 and "Traceback" not in r.stderr
    assert r.stderr.startswith("coopctl: error: coopd is not running: no control socket")


def test_stale_socket_reports_not_running(capsys):
    d = tempfile.mkdtemp(prefix="coopd-cli-", dir="/tmp")
    try:
        path = os.path.join(d, "stale.sock")
        s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        s.bind(path)
        s.close()
        assert main(["peers", "--socket", path]) == 5
        assert "nothing listens" in capsys.readouterr().err
    finally:
        shutil.rmtree(d)


@pytest.mark.skipif(os.geteuid() != 0, reason="needs root to switch to an unprivileged uid")
def test_permission_denied_message(daemon):
    """A user outside the socket's group (mode 0660) gets a clear permission message."""
    r, w = os.pipe()
    pid = os.fork()
    if pid == 0:  # child: become nobody, run coopctl, report through the pipe
        code = 99
        try:
            os.close(r)
            os.setgroups([])
            os.setgid(65534)
            os.setuid(65534)
            sys.stderr = os.fdopen(w, "w")
            code = main(["status", "--socket", daemon])
            sys.stderr.flush()
        finally:
            os._exit(code)
    os.close(w)
    with os.fdopen(r) as f:
        err = f.read()
    _, status = os.waitpid(pid, 0)
    assert os.waitstatus_to_exitcode(status) == 5
    assert "permission denied" in err and "coopd" in err and "group" in err


def test_dump_map_json_names_what_was_written(daemon, tmp_path, capsys):
    out = tmp_path / "g.ply"
    assert main(["dump-map", "global", "-o", str(out), "--json", "--socket", daemon]) == 0
    grid, meta = MAPS["global"]
    assert json.loads(capsys.readouterr().out) == {
        "file": str(out), "format": "ply", "points": grid.counts().occupied, "map": "global",
        "vehicle_id": meta.vehicle_id, "map_version": meta.version, "shape": [20, 16, 8],
        "known": grid.counts().known}


def test_dump_map_refuses_an_unknown_suffix_before_asking_the_daemon(tmp_path, capsys):
    out = tmp_path / "x.xyz"
    absent = str(tmp_path / "no-daemon.sock")  # not reached: the suffix is checked first
    assert main(["dump-map", "local", "-o", str(out), "--socket", absent]) == 2
    err = capsys.readouterr().err
    assert f"{out}: cannot tell the output format from the suffix '.xyz'" in err and "--to" in err
    assert not out.exists()


def test_dump_map_exports_follow_the_umask(daemon, tmp_path, capsys):
    old = os.umask(0o027)
    try:
        for name in ("m.cmap", "m.ply", "m.png", "m.bt"):
            assert main(["dump-map", "local", "-o", str(tmp_path / name), "--socket", daemon]) == 0
    finally:
        os.umask(old)
    capsys.readouterr()
    assert {p.name: p.stat().st_mode & 0o777 for p in tmp_path.iterdir()} == dict.fromkeys(
        ("m.cmap", "m.ply", "m.png", "m.bt"), 0o640)


def test_failures_are_json_objects_with_json(daemon, tmp_path, capsys):
    absent = str(tmp_path / "absent.sock")
    assert main(["peers", "--json", "--socket", absent]) == 5
    reply = json.loads(capsys.readouterr().out)
    assert reply["code"] == "unreachable" and reply["exit"] == 5 and "coopd is not running" in reply["error"]
    assert main(["dump-map", "7", "-o", str(tmp_path / "x.cmap"), "--json", "--socket", daemon]) == 1
    reply = json.loads(capsys.readouterr().out)
    assert reply["code"] == "failed" and reply["daemon_code"] and "no map" in reply["error"]
    assert main(["merge-now", "--json", "--socket", daemon]) == 4
    assert json.loads(capsys.readouterr().out)["outcome"] == "deferred"

"""coopd as a process against firmware_sim over real MAVLink and the camera socket: it maps the
built-in route (checked against the world's ground truth), answers coopctl, rides out link loss,
camera stalls and control-socket garbage, stops on SIGTERM with a checkpoint and resumes from it."""

import json
import os
import shutil
import socket
import struct
import subprocess
import time

import numpy as np
import pytest
from daemon_harness import PYTHON, ROOT, Coopd, NotifyListener, Sim, env, port_block, wait_until, workdir

from coopd.io import load_cmap
from coopd.sharing.wire import decode_map

pytestmark = pytest.mark.slow

MAP_SECONDS = float(os.environ.get("COOPD_DAEMON_E2E_SECONDS", "22"))


def _garbage(path: str) -> None:
    """Hostile control clients: raw junk, an oversize length, bad JSON, a client that hangs up."""
    for payload in (b"\xff" * 64, struct.pack(">I", 1 << 30), struct.pack(">I", 5) + b"{nope",
                    struct.pack(">I", 30) + b'{"v": 1, "cmd": ["status"]}   ', b""):
        s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        s.settimeout(2.0)
        try:
            s.connect(path)
            s.sendall(payload)
            s.shutdown(socket.SHUT_WR)
            try:
                s.recv(4096)
            except (TimeoutError, ConnectionResetError):
                pass
        finally:
            s.close()


def _frames(d: Coopd) -> int:
    s = d.status()
    return s["frames"]["mapped"] if s else -1


def test_daemon_maps_route_survives_faults_and_resumes():
    wd = workdir("coopd-e2e-")
    mav_port, share_port = port_block(0)
    notify = NotifyListener(wd)
    d = Coopd(wd, "a", ["--vehicle-id", "1", "--mavlink", f"udpin:127.0.0.1:{mav_port}",
                        "--camera", f"socket:{Sim.camera_path(wd, 0)}", "--sharing-port", str(share_port),
                        "--checkpoint-period", "3"],
              extra_env={"NOTIFY_SOCKET": notify.path, "WATCHDOG_USEC": "2000000"})
    sim = None
    try:
        # the companion computer boots with the FC: coopd first, then the vehicle powers up
        d.start()
        s0 = d.wait_running()
        assert s0["link"]["state"] == "connecting" and s0["camera"]["connected"] is False
        assert notify.drain(0.5) and notify.with_field("READY=1"), notify.messages
        sim = Sim(wd, mav_port, speed=2.0)
        # --- maps while the vehicle flies; coopctl status --json as an operator runs it
        assert wait_until(lambda: _frames(d) >= 20, 30), d.log_text()[-2000:]
        t_start = time.monotonic()
        s1 = d.status()
        cli = subprocess.run([PYTHON, "-m", "coopd.cli.coopctl", "status", "--json", "--socket", d.socket],
                             capture_output=True, env=env(), cwd=ROOT, timeout=30)
        assert cli.returncode == 0, cli.stderr
        s_cli = json.loads(cli.stdout)
        assert s_cli["link"]["state"] == "ok" and s_cli["vehicle_id"] == 1
        assert {t["role"] for t in s_cli["threads"]} >= {"mavlink", "camera", "mapping", "sharing",
                                                         "merging", "control"}
        assert s_cli["merging"] in ("idle", "merging") and s_cli["merges"]["available"]
        # --- map as long as the vehicle tests do (drift grows with time), compare with the truth
        time.sleep(max(0.0, MAP_SECONDS - (time.monotonic() - t_start)))
        s3 = d.status()
        assert s3, d.last_error
        assert s3["map"]["known"] > s1["map"]["known"]
        dump = wd / "local.cmap"
        cli = subprocess.run([PYTHON, "-m", "coopd.cli.coopctl", "dump-map", "local", "-o", str(dump),
                              "--socket", d.socket], capture_output=True, env=env(), cwd=ROOT, timeout=60)
        assert cli.returncode == 0, cli.stderr
        grid, meta = load_cmap(dump)
        assert meta.vehicle_id == 1 and meta.version >= s3["map"]["version"]
        acc = sim.accuracy(grid, 0, s3["link"]["map_origin_fc_enu"])
        # --- control-socket garbage: refused and counted, mapping goes on
        _garbage(d.socket)
        time.sleep(2)
        s2 = d.status()
        assert s2["control"]["bad_requests"] + s2["control"]["oversize"] >= 3, s2["control"]
        assert s2["frames"]["mapped"] > s3["frames"]["mapped"]
        assert s2["map"]["known"] >= s3["map"]["known"]
        # --- emulator stopped: link lost, odometry stale, mapping paused, camera stall counted
        sim.pause()
        paused = wait_until(lambda: (s := d.status()) and s["link"]["state"] == "lost"
                            and s["mapping"]["state"].startswith("paused") and s["camera"]["stalls"] >= 1
                            and s, 10)
        assert paused, d.status()
        frames_paused = paused["frames"]["mapped"]
        sim.resume()
        resumed = wait_until(lambda: (s := d.status()) and s["link"]["state"] == "ok"
                             and s["frames"]["mapped"] > frames_paused + 10 and s, 20)
        assert resumed, (d.status(), d.log_text()[-3000:])
        assert resumed["mapping"]["state"] == "mapping"
        notify.drain()
        watchdogs = [t for t, _ in notify.with_field("WATCHDOG=1")]
        gaps = [b - a for a, b in zip(watchdogs, watchdogs[1:], strict=False)]
        # --- SIGTERM: quick exit, final checkpoint of the final map
        before_stop = d.status()
        rc, took = d.terminate()
        notify.drain(0.2)
        newest = sorted(d.state_dir.glob("local.*.cmap"))[-1]
        cp_grid, cp_meta = load_cmap(newest)
        report = {
            "frames_in": s3["frames"]["in"], "frames_mapped": s3["frames"]["mapped"],
            "frames_dropped": s3["frames"]["dropped"], "latency_ms": s3["mapping"]["latency_ms"],
            "known_cells": [s1["map"]["known"], s3["map"]["known"]],
            "rss_mib": s3["memory"]["rss_bytes"] >> 20, "stalls": resumed["camera"]["stalls"],
            "link_losses": resumed["link"]["counters"].get("link_losses"),
            "watchdog_pings": len(watchdogs), "watchdog_gap_max_s": round(max(gaps), 3) if gaps else None,
            "sigterm_exit_s": round(took, 2), **{k: round(v, 4) if isinstance(v, float) else v
                                                 for k, v in acc.items()},
        }
        print(json.dumps(report))
        assert acc["observed_truth_cells"] > 2000, report
        assert acc["precision"] >= 0.9 and acc["recall"] >= 0.9, report
        assert len(watchdogs) >= 10 and max(gaps) < 2.0, report
        assert rc == 0 and took < 5.0, (rc, took, d.log_text()[-2000:])
        assert notify.with_field("STOPPING=1")
        assert cp_meta.version >= before_stop["map"]["version"]
        assert cp_grid.counts().known >= before_stop["map"]["known"]
        # --- restart: resumes from the checkpoint, same map frame, version continues
        d.start()
        s4 = d.wait_running()
        assert s4["map"]["version"] >= cp_meta.version
        assert s4["map"]["known"] >= cp_grid.counts().known
        assert s4["link"]["map_origin_fc_enu"] == s3["link"]["map_origin_fc_enu"]
        s5 = wait_until(lambda: (s := d.status()) and s["frames"]["mapped"] > 5 and s, 20)
        assert s5, d.log_text()[-2000:]
        assert s5["link"]["map_origin_fc_enu"] == s3["link"]["map_origin_fc_enu"]
        assert s5["map"]["version"] > cp_meta.version
        assert s5["checkpoint"]["set_aside"] == 0
    finally:
        d.stop()
        if sim is not None:
            sim.stop()
        notify.close()
    shutil.rmtree(wd, ignore_errors=True)


CONFIRM_S = 90.0
"""How long test_two_daemons_share_their_maps merges again while a vehicle's fit is provisional (quiet
machine: the right fit is confirmed about 10 s after the maps are first exchanged)."""


def merge_now(d: Coopd) -> dict:
    """`coopctl merge-now --json` on daemon d: the merge's outcome."""
    cli = subprocess.run([PYTHON, "-m", "coopd.cli.coopctl", "merge-now", "--json", "--socket", d.socket],
                         capture_output=True, text=True, env=env(), cwd=ROOT, timeout=130)
    outcome = json.loads(cli.stdout)
    assert cli.returncode == 0 and outcome["outcome"] == "done", cli
    return outcome


def offset_error(sim: Sim, statuses: list[dict], i: int, offset: dict) -> dict | None:
    """How far vehicle i's accepted offset of the other vehicle is from the simulation's truth."""
    if not offset["accepted"]:
        return None
    t_true = sim.relative_transform(i, 1 - i, statuses[i]["link"]["map_origin_fc_enu"],
                                    statuses[1 - i]["link"]["map_origin_fc_enu"])
    err = np.linalg.norm(np.array(offset["translation_m"]) - t_true[:3, 3])
    yaw_err = abs((offset["yaw_deg"] - np.degrees(np.arctan2(t_true[1, 0], t_true[0, 0])) + 180) % 360 - 180)
    return {"m": round(float(err), 3), "yaw_deg": round(float(yaw_err), 2)}


def test_two_daemons_share_their_maps():
    wd = workdir("coopd-share-")
    mav_port, share_port = port_block(1)
    sim = Sim(wd, mav_port, vehicles=2, speed=2.0)
    daemons = []
    report = {}
    try:
        for i in range(2):
            other = share_port + (1 - i)
            daemons.append(Coopd(wd, f"v{i + 1}", [
                "--vehicle-id", str(i + 1), "--mavlink", f"udpin:127.0.0.1:{mav_port + i}",
                "--camera", f"socket:{sim.camera(i)}", "--sharing-port", str(share_port + i),
                "--peer", f"127.0.0.1:{other}"]).start())
        for d in daemons:
            d.wait_running()

        def exchanged():
            out = []
            for i, d in enumerate(daemons):
                s = d.status()
                other = 2 - i
                peers = {p["vehicle_id"]: p for p in (s or {}).get("peers", [])}
                if other not in peers or peers[other]["map_version"] is None:
                    return None
                out.append(s)
            return out

        statuses = wait_until(exchanged, 45, poll=0.5)
        assert statuses, [d.status() for d in daemons]
        for i, d in enumerate(daemons):
            other = 2 - i
            # each vehicle's own map against the ground truth: the frames used for the true offset hold
            _, blob = d.request("dump-map", {"map": "local"}, max_blob_bytes=1 << 26)
            acc = sim.accuracy(decode_map(blob)[0], i, statuses[i]["link"]["map_origin_fc_enu"])
            report[f"vehicle {i + 1} map vs truth"] = {k: round(acc[k], 3) for k in ("precision", "recall")}
            assert acc["precision"] >= 0.8, report
            result, blob = d.request("dump-map", {"map": "peer", "vehicle_id": other}, max_blob_bytes=1 << 26)
            grid, meta = decode_map(blob)
            assert meta.vehicle_id == other and meta.version >= 1 and grid.counts().known > 0
            peer = {p["vehicle_id"]: p for p in statuses[i]["peers"]}[other]
            assert peer["address"].startswith("127.0.0.1")
            assert statuses[i]["memory"]["entries"].get(f"received:{other}", 0) > 0 or wait_until(
                lambda d=d, other=other: d.status()["memory"]["entries"].get(f"received:{other}"), 3)
            # A fit newly found by a search is provisional: held out of the global map and not published
            # until a recheck on grown maps finds it again. Early in the flight the two maps share little
            # and a look-alike room can validate (a fit 16 m and 90 degrees off, held, then replaced by
            # the right one): merge again while the fit is provisional, bounded by CONFIRM_S.
            deadline, rounds = time.monotonic() + CONFIRM_S, []
            while True:
                outcome = merge_now(d)
                offset = d.status()["merges"]["offsets"][str(other)]
                assert set(offset) >= {"accepted", "score", "reason", "translation_m", "yaw_deg", "transform"}
                assert (offset["reason"] == "accepted") == offset["accepted"]
                rounds.append({k: offset[k] for k in ("accepted", "provisional", "method", "reason")}
                              | {"error_vs_truth": offset_error(sim, statuses, i, offset)})
                if (offset["accepted"] and not offset["provisional"]) or time.monotonic() > deadline:
                    break
                time.sleep(2.0)
            report[f"vehicle {i + 1}"] = {"merge": outcome, f"offset of vehicle {other}": offset,
                                          "rounds": rounds}
            assert offset["accepted"] and not offset["provisional"], report
            # a confirmed fit is fused and published: it must be the true one
            error = rounds[-1]["error_vs_truth"]
            assert error["m"] < 0.3 and error["yaw_deg"] < 2.0, report
            merges = d.status()["merges"]
            assert merges["global_version"] >= 1
            assert merges["full_registrations"] + merges["hinted"] >= 1 and merges["cpu_s"] > 0
            # distributed merging: our validated transform reaches the peer as a merge result
            peer, vid = daemons[1 - i], str(i + 1)
            assert wait_until(lambda p=peer, v=vid: v in p.status()["sharing"]["received_results"], 15,
                              poll=0.5), (report, peer.status()["sharing"])
        print(json.dumps(report))
        # received maps are checkpointed on stop and restored on start
        rc, _ = daemons[0].terminate()
        assert rc == 0
        assert list(daemons[0].state_dir.glob("peer-2.*.cmap"))
        daemons[0].start()
        s = daemons[0].wait_running()
        assert "2" in s["sharing"]["received_maps"], s["sharing"]
        assert s["memory"]["entries"].get("received:2", 0) > 0 or wait_until(  # accounted each main loop
            lambda: daemons[0].status()["memory"]["entries"].get("received:2"), 3)
        # restarted with a memory budget only ~2 MiB above the interpreter's own RSS, vehicle 2's map
        # could never be merged: it is set aside at start (not restored to defer every merge) and
        # refused when vehicle 2 sends it again, before it is decoded
        baseline_mib = statuses[0]["memory"]["baseline_bytes"] >> 20
        rc, _ = daemons[0].terminate()
        assert rc == 0
        daemons[0].args += ["--memory-mb", str(baseline_mib + 2)]
        daemons[0].start()
        s = daemons[0].wait_running()
        assert "2" not in s["sharing"]["received_maps"], s["sharing"]
        assert any("peer-2" in p and "can merge" in p for p in s["checkpoint"]["problems"]), s["checkpoint"]
        assert wait_until(lambda: (daemons[0].status()["sharing"]["peers"] or [{}])[0].get("failures", {})
                          .get("oversize", 0) >= 1, 30, poll=0.5), daemons[0].status()["sharing"]
        cli = subprocess.run([PYTHON, "-m", "coopd.cli.coopctl", "merge-now", "--socket", daemons[0].socket],
                             capture_output=True, text=True, env=env(), cwd=ROOT, timeout=130)
        assert cli.returncode == 0 and "deferred" not in cli.stdout, (cli, s["memory"], s["map"]["cells"])
        merges = daemons[0].status()["merges"]
        assert merges["deferred"] == 0, merges
        memory = daemons[0].status()["memory"]
        report["tight budget"] = {"merge-now": cli.stdout.strip(), "MiB": {
            k: memory[k] >> 20 for k in ("budget_bytes", "baseline_bytes", "rss_bytes")}}
        print(json.dumps(report["tight budget"]))
    finally:
        for d in daemons:
            d.stop()
        sim.stop()
    shutil.rmtree(wd, ignore_errors=True)

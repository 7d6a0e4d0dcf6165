"""The Daemon in-process without a vehicle: command line and config errors, control commands,
sd_notify READY/STATUS/WATCHDOG (withheld while the mapping thread hangs, never blocking on a full
notify queue), resume from checkpoints with the map frame, and the merging wiring."""

import json
import os
import shutil
import socket
import sys
import threading
import time
import types
from contextlib import contextmanager
from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest
from daemon_harness import (
    NotifyListener,
    in_process_memory_mb,
    port_block,
    swarm_key_file,
    wait_until,
    workdir,
)

from coopd.daemon import control
from coopd.daemon.budget import MemoryBudget
from coopd.daemon.checkpoint import CheckpointStore, VersionReserve
from coopd.daemon.config import from_dict
from coopd.daemon.main import main
from coopd.daemon.merge_state import MergerSettings, MergeSources
from coopd.daemon.merger import NOT_AVAILABLE, Merger, find_merge_all
from coopd.daemon.notify import Notifier
from coopd.daemon.service import FRAME_FILE, FROM_BUILD, Daemon, StartupError, save_map_frame
from coopd.geometry import rigid, rotation_z
from coopd.grid import OccupancyGrid, fuse_transformed
from coopd.sharing.wire import MapMeta, decode_map, encode_map


def _config(wd, **daemon_keys):
    mav, _ = port_block(3)
    return from_dict({
        "vehicle": {"mavlink": f"udpin:127.0.0.1:{mav}"},
        "camera": {"source": f"socket:{wd}/no-camera.sock"},
        "sharing": {"enabled": False},
        "daemon": {"state_dir": str(wd / "state"), "control_socket": str(wd / "control.sock"),
                   "memory_mb": in_process_memory_mb(), **daemon_keys},
    })


@pytest.fixture
def wd():
    d = workdir("coopd-svc-")
    yield d
    shutil.rmtree(d, ignore_errors=True)


def _box_grid(offset=(0, 0, 0)) -> OccupancyGrid:
    g = OccupancyGrid.empty((30, 30, 10), 0.1)
    keys = np.array([[x, y, 2] for x in range(-5, 6) for y in range(-5, 6)]) + np.array(offset)
    g.set_keys(keys, 0)
    g.set_keys(np.array([[x, 5, z] for x in range(-5, 6) for z in range(0, 4)]) + np.array(offset), 90)
    return g


# ------------------------------------------------------------------------------------ command line
def test_command_line_and_config_errors(wd, capsys):
    assert main(["--config", str(wd / "missing.toml")]) == 2
    assert "configuration" in capsys.readouterr().err
    assert main(["--no-config", "--vehicle-id", "0", "--check-config"]) == 2
    assert "vehicle.id: 0 is outside 1..255" in capsys.readouterr().err
    (wd / "c.toml").write_text('[vehicle]\nidd = 3\n')
    assert main(["--config", str(wd / "c.toml"), "--check-config"]) == 2
    assert "vehicle.idd: unknown key" in capsys.readouterr().err
    assert main(["--no-config", "--vehicle-id", "7", "--peer", "127.0.0.1:7401", "--check-config"]) == 0
    assert "vehicle 7" in capsys.readouterr().out


def test_help_names_the_exit_codes(capsys):
    with pytest.raises(SystemExit) as exit_:
        main(["--help"])
    assert exit_.value.code == 0
    text = " ".join(capsys.readouterr().out.split())
    assert "exit codes: 0 stopped by SIGTERM/SIGINT (final checkpoint written), 1 could not start, 2 bad " \
        "command line or configuration" in text


def test_second_daemon_on_a_served_control_socket_refuses_to_start(wd):
    cfg = _config(wd)
    with control.ControlServer(cfg.daemon.control_socket, {}):
        d = Daemon(cfg)
        with pytest.raises(StartupError, match="another process is serving"):
            d.start()
        d.shutdown()


# ---------------------------------------------------------------------------------- control, notify
@pytest.mark.parametrize("merging", ["this build", "not in the build"])
def test_commands_without_a_vehicle(wd, merging):
    budget_mb = in_process_memory_mb(400)
    d = Daemon(_config(wd, memory_mb=budget_mb), merge_fn=FROM_BUILD if merging == "this build" else None)
    d.start()
    runner = threading.Thread(target=d.run, daemon=True)
    runner.start()
    try:
        status, _ = control.request(d.config.daemon.control_socket, "status")
        json.dumps(status, allow_nan=False)
        assert status["state"] == "running" and status["vehicle_id"] == 1
        assert status["link"]["state"] == "connecting" and status["pose"] is None
        assert status["mapping"]["state"].startswith("paused: odometry stale")
        assert status["merging"] == ("idle" if merging == "this build" else NOT_AVAILABLE)
        assert status["memory"]["budget_bytes"] == budget_mb << 20
        assert status["memory"]["entries"]["local"] > 0 and not status["memory"]["over_budget"]
        assert d.camera.fc is d.link  # an FC reboot seen by the link resets the camera's time reference
        roles = {t["role"]: t for t in status["threads"]}
        assert set(roles) >= {"mavlink", "camera", "mapping", "merging", "control"}
        assert roles["merging"]["applied"] == 10
        assert control.request(d.config.daemon.control_socket, "peers")[0] == {"peers": []}
        part, _ = control.request(d.config.daemon.control_socket, "status", {"sections": ["merges", "peers"]})
        assert set(part) == {"vehicle_id", "pid", "state", "uptime_s", "merges", "peers"}, part
        assert part["merges"]["state"] == status["merges"]["state"] and part["peers"] == []
        with pytest.raises(control.ControlError, match=r"unknown status sections \['offsets'\]"):
            control.request(d.config.daemon.control_socket, "status", {"sections": ["merges", "offsets"]})
        merge, _ = control.request(d.config.daemon.control_socket, "merge-now")
        result, blob = control.request(d.config.daemon.control_socket, "dump-map", {"map": "global"},
                                       max_blob_bytes=1 << 20)
        if merging == "this build":
            assert merge["outcome"] == "done" and "no received maps" in merge["detail"]
            assert result["note"] == "no merge yet: the global map is the local map"
        else:
            assert merge == {"outcome": "failed", "detail": NOT_AVAILABLE}
            assert "not available" in result["note"]
        grid, meta = decode_map(blob)
        assert meta.vehicle_id == 1
        for bad in ({"map": "peer", "vehicle_id": 9}, {"map": "peer", "vehicle_id": "x"}, {"map": "moon"}):
            with pytest.raises(control.RemoteError):
                control.request(d.config.daemon.control_socket, "dump-map", bad, max_blob_bytes=1 << 20)
    finally:
        d.request_stop("test")
        runner.join(5)
        d.shutdown()
    assert not os.path.exists(d.config.daemon.control_socket)


def test_sd_notify_ready_status_and_watchdog_only_while_mapping_lives(wd):
    listener = NotifyListener(wd)
    notifier = Notifier("socket", {"NOTIFY_SOCKET": listener.path, "WATCHDOG_USEC": "400000"})
    d = Daemon(_config(wd), notifier=notifier)
    hang = threading.Event()
    real_take = d.slot.take

    def take(timeout=0.0):
        if hang.is_set():
            release.wait(30)
        return real_take(timeout)

    release = threading.Event()
    d.slot.take = take
    d.start()
    runner = threading.Thread(target=d.run, daemon=True)
    runner.start()
    try:
        assert wait_until(lambda: listener.with_field("READY=1"), 5)
        time.sleep(1.5)
        pings = [t for t, _ in listener.with_field("WATCHDOG=1")]
        gaps = np.diff(pings)
        assert len(pings) >= 5 and 0.1 < gaps.mean() < 0.35, gaps
        assert listener.with_field("STATUS=running: link connecting")
        hang.set()  # the mapping thread stops looping: after HEALTH_MAX_AGE_S the pings stop
        time.sleep(4.0)
        t_quiet = time.monotonic()
        time.sleep(1.0)
        assert not [t for t, _ in listener.with_field("WATCHDOG=1") if t > t_quiet]
        assert d.watchdog.withheld > 0 and not d.healthy()
        release.set()
        hang.clear()
        assert wait_until(lambda: [t for t, _ in listener.with_field("WATCHDOG=1") if t > t_quiet + 1.0], 3)
    finally:
        release.set()
        d.request_stop("test")
        runner.join(5)
        d.shutdown()
        listener.close()
    assert listener.with_field("STOPPING=1")


@contextmanager
def _running(d: Daemon, listener: NotifyListener, *releases: threading.Event):
    """d runs in a thread until the block ends; then the events are set (a hung step goes on), d
    stops and the listener closes."""
    d.start()
    runner = threading.Thread(target=d.run, daemon=True)
    runner.start()
    try:
        yield
    finally:
        for e in releases:
            e.set()
        d.request_stop("test")
        runner.join(5)
        d.shutdown()
        listener.close()


def _pings_after(listener, t: float) -> list[float]:
    return [tp for tp, _ in listener.with_field("WATCHDOG=1") if tp > t]


@pytest.mark.parametrize("worker", ["merging", "sharing"])
def test_a_hung_merging_or_sharing_thread_stops_the_watchdog_and_is_logged(wd, worker, caplog):
    """A merge that computes for 5 s keeps the pings going; a merge or a publish blocked on a lock
    (no CPU) stops them once it used no CPU for busy_quiet_s, with one ERROR line naming the thread
    and the thread shown in status; released, the pings come back."""
    listener = NotifyListener(wd)
    notifier = Notifier("socket", {"NOTIFY_SOCKET": listener.path, "WATCHDOG_USEC": "400000"})
    _, share_port = port_block(3)
    cfg = _config(wd)
    if worker == "sharing":
        sharing = replace(cfg.sharing, enabled=True, port=share_port, listen_host="127.0.0.1",
                          swarm_key_file=str(swarm_key_file(wd)))
        cfg = replace(cfg, sharing=sharing)
    d = Daemon(cfg, notifier=notifier)
    d.progress.busy_quiet_s = 1.0
    release = threading.Event()
    real_merge = d.merger._merge

    def merge(mode=["spin"]):  # noqa: B006 (the test switches the mode)
        if mode[0] == "spin":
            t_end = time.monotonic() + 5.0  # a long merge: bounded arithmetic
            while time.monotonic() < t_end:
                sum(range(1000))
            mode[0] = "block"
            return real_merge()
        release.wait(30)
        return real_merge()

    d.merger._merge = merge
    caplog.set_level("INFO", logger="coopd.daemon")
    d.start()
    runner = threading.Thread(target=d.run, daemon=True)
    runner.start()
    try:
        assert wait_until(lambda: listener.with_field("READY=1"), 5)
        if worker == "merging":
            d.merger.request("test", urgent=True)
            time.sleep(0.5)
            assert d.merger.busy_since is not None
            t_spin = time.monotonic()
            time.sleep(4.0)  # computing past the 3 s loop window: still healthy
            assert len(_pings_after(listener, t_spin)) >= 10 and d.healthy()
            assert wait_until(lambda: d.merger.busy_since is None, 5)
            d.merger.request("test", urgent=True)  # this one blocks
        else:
            d._message_lock.acquire()  # a publish that never gets the lock
            d.mapper.version = 1
        t_hang = time.monotonic()
        time.sleep(4.5)  # 3 s without looping, 1 s of it without CPU, and the watchdog's interval
        t_quiet = time.monotonic()
        time.sleep(1.0)
        assert not _pings_after(listener, t_quiet), d.progress.stalled()
        last = max(t for t, _ in listener.with_field("WATCHDOG=1"))
        print(f"{worker} hung: last WATCHDOG=1 {last - t_hang:.2f} s after the hang; {d.stalled_threads()}")
        status, _ = control.request(d.config.daemon.control_socket, "status")
        assert not status["watchdog"]["healthy"] and list(status["watchdog"]["stalled_threads"]) == [worker]
        errors = [r.getMessage() for r in caplog.records
                  if r.levelname == "ERROR" and worker in r.getMessage()]
        assert len(errors) == 1 and "without using CPU" in errors[0], errors
        if worker == "merging":
            release.set()
        else:
            d._message_lock.release()
        assert wait_until(lambda: _pings_after(listener, t_quiet + 1.0), 5)
        assert any("makes progress again" in r.getMessage() for r in caplog.records)
    finally:
        release.set()
        if worker == "sharing" and d._message_lock.locked():
            d._message_lock.release()
        d.request_stop("test")
        runner.join(5)
        d.shutdown()
        listener.close()


def test_a_hung_obstacle_feed_stops_the_watchdog(wd, caplog):
    """The flight controller's obstacle feed is watched like the other workers: an update blocked (on
    the mapping lock, say) stops the pings with one ERROR line naming the thread; released, they resume."""
    listener = NotifyListener(wd)
    notifier = Notifier("socket", {"NOTIFY_SOCKET": listener.path, "WATCHDOG_USEC": "400000"})
    cfg = replace(_config(wd), obstacles=replace(_config(wd).obstacles, enabled=True))
    d = Daemon(cfg, notifier=notifier)
    assert "obstacles" in d.progress.watched()
    hang, release = threading.Event(), threading.Event()
    updates = []

    def update():
        updates.append(time.monotonic())
        if hang.is_set():
            release.wait(30)

    d.obstacles.update = update
    caplog.set_level("INFO", logger="coopd.daemon")
    with _running(d, listener, release):
        assert wait_until(lambda: listener.with_field("READY=1") and len(updates) > 10, 5)
        assert d.healthy()
        hang.set()
        time.sleep(3.5)  # 3 s without looping, and the watchdog's interval
        t_quiet = time.monotonic()
        time.sleep(1.0)
        assert not _pings_after(listener, t_quiet), d.progress.stalled()
        assert list(d.stalled_threads()) == ["obstacles"]
        errors = [r.getMessage() for r in caplog.records
                  if r.levelname == "ERROR" and r.getMessage().startswith("thread obstacles")]
        assert len(errors) == 1 and "has not looped" in errors[0], errors
        hang.clear()
        release.set()
        assert wait_until(lambda: _pings_after(listener, t_quiet + 1.0), 5)


def test_a_build_without_merging_is_a_warning_not_an_error(caplog, monkeypatch):
    monkeypatch.setitem(sys.modules, "coopd.merging", None)  # the package is not installed
    caplog.set_level("INFO", logger="coopd.daemon")
    assert find_merge_all() == (None, None)
    assert [r.levelname for r in caplog.records if NOT_AVAILABLE in r.getMessage()] == ["WARNING"]


def test_an_import_error_inside_merging_is_an_error_line_and_shown_in_status(wd, caplog, monkeypatch):
    """A broken coopd.merging (here: merge_all missing, as a half-installed build) turns merging
    off with an ERROR line and the reason in status and merge-now, not just a state field."""
    monkeypatch.setitem(sys.modules, "coopd.merging", types.ModuleType("coopd.merging"))
    caplog.set_level("INFO", logger="coopd.daemon")
    d = Daemon(_config(wd))
    errors = [r.getMessage() for r in caplog.records if r.levelname == "ERROR"]
    assert any("merging is off: importing coopd.merging failed: ImportError" in e for e in errors), errors
    d.start()
    try:
        status, _ = control.request(d.config.daemon.control_socket, "status")
        assert status["merging"].startswith("merging: off: importing coopd.merging failed: ImportError")
        assert "merge_all" in status["merges"]["start_error"]
        merge, _ = control.request(d.config.daemon.control_socket, "merge-now")
        assert merge["outcome"] == "failed" and "ImportError" in merge["detail"]
    finally:
        d.shutdown()


def test_rss_over_the_budget_is_logged_once_per_crossing_and_shown_in_status(wd, caplog):
    """The process grows 160 MiB over a budget set 80 MiB above its RSS, stays there, shrinks back,
    grows again: one WARNING with the numbers per crossing, one INFO per return, status says so."""
    d = Daemon(_config(wd))
    budget_mb = (d.budget.rss() >> 20) + 80  # above what the daemon (kernels loaded) holds now
    d.budget.budget_bytes = budget_mb << 20
    caplog.set_level("INFO", logger="coopd.daemon")
    d.start()
    runner = threading.Thread(target=d.run, daemon=True)
    runner.start()

    def memory():
        return control.request(d.config.daemon.control_socket, "status")[0]["memory"]

    try:
        assert not memory()["over_budget"]
        for crossing in (1, 2):
            ballast = np.ones(160 << 20, np.uint8)  # touched: resident
            assert wait_until(lambda: memory()["over_budget"], 5)
            time.sleep(1.0)  # five more checks while over: no more lines
            m = memory()
            assert m["over_budget_crossings"] == crossing and m["rss_over_budget"]
            assert m["over_budget_for_s"] >= 1
            del ballast
            assert wait_until(lambda: not memory()["over_budget"], 5)
        over = [r.getMessage() for r in caplog.records if "over the budget" in r.getMessage()]
        back = [r.getMessage() for r in caplog.records if "back under the budget" in r.getMessage()]
        print(over[0], back[0], sep="\n")
        assert len(over) == 2 and len(back) == 2
        assert f"over the budget of {budget_mb} MiB (memory_mb)" in over[0] and "crossing 2" in over[1]
        assert all(r.levelname == "WARNING" for r in caplog.records if "over the budget" in r.getMessage())
    finally:
        d.request_stop("test")
        runner.join(5)
        d.shutdown()


def test_a_notify_queue_nobody_reads_never_blocks_the_daemon(wd):
    deaf = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    deaf.bind(str(wd / "deaf.sock"))
    notifier = Notifier("socket", {"NOTIFY_SOCKET": str(wd / "deaf.sock"), "WATCHDOG_USEC": "100000"})
    d = Daemon(_config(wd), notifier=notifier)
    d.start()
    runner = threading.Thread(target=d.run, daemon=True)
    runner.start()
    try:
        assert wait_until(lambda: notifier.dropped > 5, 10)
        t0 = time.monotonic()
        status, _ = control.request(d.config.daemon.control_socket, "status", timeout_s=5)
        assert time.monotonic() - t0 < 2.0 and status["watchdog"]["notify_dropped"] > 5
        assert d.healthy()
    finally:
        d.request_stop("test")
        runner.join(5)
        d.shutdown()
        deaf.close()


# ------------------------------------------------------------------------------------------ resume
def test_resume_from_checkpoint_keeps_version_cells_and_map_frame(wd):
    cfg = _config(wd)
    store = CheckpointStore(cfg.daemon.state_dir)
    grid = _box_grid()
    store.save("local", grid, MapMeta(1, 41))
    store.save("local", grid, MapMeta(1, 42))
    save_map_frame(wd / "state", 1, [1.5, -2.0, 0.25])
    newest = store.generations("local")[0][1]
    newest.write_bytes(newest.read_bytes()[:-7])  # torn: the older generation is loaded
    d = Daemon(cfg)
    assert d.mapper.version == 41
    assert d.mapper.grid.same_cells(grid)
    assert d.mapper.grid.growth.max_cells <= d.budget.grid_budget // 4
    np.testing.assert_allclose(d.link.odometry.origin_enu, [1.5, -2.0, 0.25])
    assert d.store.set_aside == 1
    d.mapper.version = 45
    d.checkpoint()
    _, meta = decode_map(store.generations("local")[0][1].read_bytes())
    assert meta.version == 45
    d.mapper.close()


def test_resume_after_kill9_continues_above_every_version_it_may_have_published(wd):
    """Regression (swarm fault matrix): a daemon killed -9 three versions after its last checkpoint
    resumed at the checkpoint's version, so peers held a different map under the versions it
    published next."""
    cfg = _config(wd)
    store = CheckpointStore(cfg.daemon.state_dir)
    store.save("local", _box_grid(), MapMeta(1, 77))
    (wd / "state" / FRAME_FILE).write_text(json.dumps({"vehicle_id": 1, "origin_fc_enu": [0, 0, 0]}))
    VersionReserve(cfg.daemon.state_dir).ensure(80)  # v78..v80 went out before the kill
    d = Daemon(cfg)
    assert d.mapper.version > 80 and d.mapper.grid.counts().known > 0
    d.mapper.close()


@pytest.mark.parametrize("frame", ["missing", "other vehicle", "garbage"])
def test_no_resume_without_a_valid_map_frame(wd, frame):
    cfg = _config(wd)
    CheckpointStore(cfg.daemon.state_dir).save("local", _box_grid(), MapMeta(1, 9))
    text = {"missing": None, "other vehicle": json.dumps({"vehicle_id": 2, "origin_fc_enu": [0, 0, 0]}),
            "garbage": "\x00{[not json"}[frame]
    if text is not None:
        (wd / "state" / FRAME_FILE).write_text(text)
    d = Daemon(cfg)
    assert d.mapper.version == 0 and d.mapper.grid.counts().known == 0
    assert d.link.odometry.origin_enu is None
    d.mapper.close()


# ----------------------------------------------------------------------------------------- merging
def _stored(vid, grid, version=1):
    return SimpleNamespace(vehicle_id=vid, version=version, data=encode_map(grid, MapMeta(vid, version)))


def _one_map_sources(**more) -> MergeSources:
    """A local box map at version 3 and vehicle 2's box map received (`more`: further sources)."""
    return MergeSources(lambda: (_box_grid(), 3), lambda: [_stored(2, _box_grid())], **more)


def test_merger_fuses_accepted_maps_with_their_transform_and_defers_over_budget():
    local = _box_grid()
    t = rigid(rotation_z(np.pi / 2), [3.0, 0.0, 0.0])  # vehicle 5's frame -> ours
    other = _box_grid(offset=(0, 0, 0))
    other.set_keys(np.array([[0, -5, 3]]), 100)  # a cell only vehicle 5 knows
    calls = []

    def merge_all(reference, others, params, hints=None):
        """What coopd.merging.merge_all returns: the fused global map and one result per input map,
        here with the answer known in advance (vehicle 5 at t, vehicle 6 not overlapping)."""
        calls.append(len(others))
        world = reference.copy()
        fuse_transformed(world, others[0], t)
        return SimpleNamespace(global_map=world, rounds=1, results=[
            SimpleNamespace(accepted=True, transform=t, score=0.8, reason="accepted"),
            SimpleNamespace(accepted=False, transform=np.eye(4), score=0.1, reason="overlap too small")])

    received = [_stored(6, _box_grid(offset=(40, 0, 0))), _stored(5, other)]  # merged in vehicle id order
    budget = MemoryBudget(64 << 20, baseline_bytes=0)
    sources = MergeSources(lambda: (local.copy(), 7), lambda: received)
    m = Merger(1, MergerSettings(period_s=3600), sources, budget, merge_fn=merge_all)
    out = m.merge_once("test")
    assert out["outcome"] == "done", out
    merged, meta = m.global_map()
    # the cell (0, -5, 3) of vehicle 5 lands at R p + t = (3.5, 0, 0.3) m in our frame
    assert merged.values_at(np.array([[3.5, 0.0, 0.3]]))[0] == 100
    assert merged.values_at(np.array([[3.0, 0.0, 0.2]]))[0] == 0  # its floor, moved
    assert local.values_at(np.array([[3.0, 0.0, 0.2]]))[0] == -1
    assert merged.values_at(np.array([[4.0, 0.0, 0.2]]))[0] == -1  # vehicle 6 was not accepted
    assert merged.values_at(np.array([[0.0, 0.0, 0.2]]))[0] == 0  # our own map is kept
    assert m.offsets[5]["accepted"] and m.offsets[5]["translation_m"] == [3.0, 0.0, 0.0]
    assert m.offsets[5]["yaw_deg"] == 90.0 and not m.offsets[6]["accepted"]
    assert m.offsets[6]["reason"] == "overlap too small"
    assert "1 of 2 received maps merged [5]" in out["detail"]
    assert meta.version == 1 and budget.snapshot()["entries"]["global"] == merged.size
    assert "merge-scratch" not in budget.snapshot()["entries"]
    # a budget too small for the decompressed maps: deferred, the last global map is kept
    tight = Merger(1, MergerSettings(period_s=3600), sources, MemoryBudget(20_000, baseline_bytes=0),
                   merge_fn=merge_all)
    out = tight.merge_once("test")
    assert out["outcome"] == "deferred" and "memory budget" in out["detail"]
    assert tight.global_map() is None and tight.counters["deferred"] == 1 and len(calls) == 1


def test_merger_thread_merges_on_request_and_reports_failures():
    def broken(reference, others, params):
        raise RuntimeError("no overlap")

    budget = MemoryBudget(64 << 20, baseline_bytes=0)
    m = Merger(1, MergerSettings(period_s=3600), _one_map_sources(), budget, merge_fn=broken)
    runner = threading.Thread(target=m.run, daemon=True)
    runner.start()
    try:
        out = m.merge_now(10)
        assert out["outcome"] == "failed" and "no overlap" in out["detail"]
        assert m.status()["failed"] == 1 and m.status()["state"] == "idle"
    finally:
        m.stop()
        runner.join(5)
    assert not runner.is_alive()


def test_unchanged_inputs_are_not_merged_again_but_new_versions_and_merge_now_are():
    calls = []

    def merge_all(reference, others, params, hints=None):
        calls.append(len(others))
        return SimpleNamespace(global_map=reference.copy(), rounds=1, results=[
            SimpleNamespace(accepted=True, transform=np.eye(4), score=1.0, reason="test") for _ in others])

    received = [_stored(2, _box_grid())]
    local = {"version": 3}
    budget = MemoryBudget(64 << 20, baseline_bytes=0)
    sources = MergeSources(lambda: (_box_grid(), local["version"]), lambda: list(received),
                           local_version=lambda: local["version"])
    m = Merger(1, MergerSettings(period_s=0.2), sources, budget, merge_fn=merge_all)
    runner = threading.Thread(target=m.run, daemon=True)
    runner.start()
    try:
        assert wait_until(lambda: m.counters["unchanged"] >= 3, 5.0)  # periods and requests, one merge
        m.request("map of vehicle 2 v1")
        assert wait_until(lambda: m.counters["unchanged"] >= 4, 5.0) and calls == [1]
        received.append(_stored(3, _box_grid(), version=4))  # a new peer map: merged
        assert wait_until(lambda: len(calls) == 2, 5.0) and calls == [1, 2]
        local["version"] = 4  # the local map changed: merged
        assert wait_until(lambda: len(calls) == 3, 5.0)
        assert m.merge_now(10)["outcome"] == "done" and len(calls) == 4  # the operator asked: always
        assert m.status()["done"] == 4 and m.status()["unchanged"] >= 4
    finally:
        m.stop()
        runner.join(5)


def _timed_merger(settings: MergerSettings) -> tuple[Merger, list[float], threading.Thread]:
    """A running Merger on one received map whose merge_all accepts everything and notes when it ran."""
    calls = []

    def merge_all(reference, others, params, hints=None):
        calls.append(time.monotonic())
        return SimpleNamespace(global_map=reference.copy(), rounds=1, results=[
            SimpleNamespace(accepted=True, transform=np.eye(4), score=1.0, reason="test") for _ in others])

    m = Merger(1, settings, _one_map_sources(), MemoryBudget(64 << 20, baseline_bytes=0), merge_fn=merge_all)
    m.merge_once("warm-up")  # compiled kernels loaded before anything is timed (a test run alone)
    calls.clear()
    runner = threading.Thread(target=m.run, daemon=True)
    runner.start()
    return m, calls, runner


def test_received_maps_merge_once_settled_and_at_most_a_gap_after_the_first():
    m, calls, runner = _timed_merger(MergerSettings(period_s=3600, min_gap_s=1.5, settle_s=0.5))
    try:
        t0 = time.monotonic()
        for _ in range(3):  # a burst of maps: one merge, settle_s after the last
            m.request("map")
            time.sleep(0.2)
        assert wait_until(lambda: calls, 5.0)
        assert 0.85 <= calls[0] - t0 <= 1.5 and len(calls) == 1
        t1 = time.monotonic()
        while time.monotonic() - t1 < 4.0:  # maps that never stop: merged every min_gap_s all the same
            m.request("map")
            time.sleep(0.1)
        assert 2 <= len(calls) - 1 <= 3, np.diff(calls)
        assert calls[1] - t1 <= 1.5 + 0.5
    finally:
        m.stop()
        runner.join(5)


def test_first_maps_of_a_swarm_arriving_longer_than_a_gap_merge_in_one_go():
    """A vehicle's first map is a new map: while new ones keep coming (a swarm's first exchange
    spread over more than min_gap_s), the merge waits for the last; a vehicle's next versions do not
    extend the wait (a peer publishing every second still merges every min_gap_s)."""
    m, calls, runner = _timed_merger(MergerSettings(period_s=3600, min_gap_s=0.6, settle_s=0.3))
    try:
        t0 = time.monotonic()
        for vid in range(2, 10):  # eight first maps over 1.4 s, 0.2 s apart
            m.on_map(vid, 1)
            time.sleep(0.2)
        assert wait_until(lambda: calls, 5.0)
        assert calls[0] - t0 >= 1.4 + 0.3 - 0.05 and len(calls) == 1
        t1 = time.monotonic()
        for version in range(2, 10):  # vehicle 2's next versions for 1.6 s: merged within a gap
            m.on_map(2, version)
            time.sleep(0.2)
        assert len(calls) >= 2 and calls[1] - t1 <= 0.6 + 0.5, np.diff(calls)
    finally:
        m.stop()
        runner.join(5)


def test_received_maps_merge_at_most_once_per_gap_but_merge_now_at_once():
    calls = []

    def merge_all(reference, others, params, hints=None):
        calls.append(time.monotonic())
        return SimpleNamespace(global_map=reference.copy(), rounds=1, results=[
            SimpleNamespace(accepted=False, transform=np.eye(4), score=0.0, reason="test")])

    budget = MemoryBudget(64 << 20, baseline_bytes=0)
    settings = MergerSettings(period_s=3600, min_gap_s=1.0)
    m = Merger(1, settings, _one_map_sources(), budget, merge_fn=merge_all)
    runner = threading.Thread(target=m.run, daemon=True)
    runner.start()
    try:
        for _ in range(15):  # a peer publishing ten times a second for 1.5 s
            m.request("map of vehicle 2")
            time.sleep(0.1)
        assert 1 <= len(calls) <= 3, np.diff(calls)
        assert all(g >= 0.9 for g in np.diff(calls))
        t0 = time.monotonic()
        assert m.merge_now(10)["outcome"] == "done"
        assert time.monotonic() - t0 < 0.8
    finally:
        m.stop()
        runner.join(5)


def test_peers_results_stop_counting_once_every_map_is_merged():
    """A distributed merger that left a map out merges again when a peer's result arrives; once
    everything is merged, further results (peers publishing theirs) do not trigger merges."""
    calls = []
    accept = {"now": False}

    def merge_all(reference, others, params, hints=None, hints_only=frozenset(), recheck=frozenset()):
        calls.append(len(others))
        return SimpleNamespace(global_map=reference.copy(), rounds=1, results=[
            SimpleNamespace(accepted=accept["now"], transform=np.eye(4), score=1.0, reason="test")
            for _ in others])

    results = []
    budget = MemoryBudget(64 << 20, baseline_bytes=0)
    sources = _one_map_sources(local_version=lambda: 3, peer_results=lambda: list(results))
    m = Merger(1, MergerSettings(period_s=0.2, distributed=True), sources, budget, merge_fn=merge_all)
    runner = threading.Thread(target=m.run, daemon=True)
    runner.start()
    try:
        assert wait_until(lambda: m.counters["unchanged"] >= 2, 5.0) and calls == [1]  # map 2 left out
        accept["now"] = True
        results.append(SimpleNamespace(vehicle_id=2, version=1, edges=()))
        assert wait_until(lambda: len(calls) == 2, 5.0)  # a new result while a map is left out
        unchanged = m.counters["unchanged"]
        results.append(SimpleNamespace(vehicle_id=3, version=1, edges=()))
        assert wait_until(lambda: m.counters["unchanged"] >= unchanged + 3, 5.0)
        assert len(calls) == 2  # everything merged: results no longer count
    finally:
        m.stop()
        runner.join(5)


def test_a_refused_map_version_starts_a_new_epoch_and_the_map_is_published_again(wd):
    """A peer holding a forged newer version of our map refuses ours: the daemon publishes it again
    in a new version epoch (from the clock, above every earlier one, also after a restart)."""
    from coopd.daemon import service as daemon_service
    from coopd.sharing.mtp import ACK_VERSION

    d = Daemon(_config(wd))
    first = d.epoch
    assert VersionReserve(d.state_dir).epoch == first  # written: a restart starts above it
    d._published_version = 12
    d._epoch_at -= daemon_service.NEW_EPOCH_MIN_S
    d.epoch -= 5  # as if started five seconds ago
    d._own_map_refused(2, 1234, ACK_VERSION)
    d._maybe_new_epoch()
    assert d.epoch > first and d._published_version == 0 and VersionReserve(d.state_dir).epoch == d.epoch
    assert d._own_refusal is None
    again = Daemon(_config(wd))
    assert again.epoch > d.epoch
    d.mapper.close()
    again.mapper.close()


def test_maps_evicted_from_the_store_leave_no_checkpoint_to_come_back(tmp_path):
    """Made-up vehicles that filled the store and were evicted must not return after a restart."""
    from coopd.sharing.peers import MessageSummary

    cfg = from_dict({
        "vehicle": {"mavlink": "udpin:127.0.0.1:21170"},
        "camera": {"source": f"socket:{tmp_path}/no-camera.sock"},
        "sharing": {"listen_host": "127.0.0.1", "port": 21171,
                    "swarm_key_file": str(swarm_key_file(tmp_path))},
        "daemon": {"state_dir": str(tmp_path / "state"), "control_socket": str(tmp_path / "control.sock"),
                   "memory_mb": in_process_memory_mb()},
    })
    d = Daemon(cfg)
    try:
        grid = OccupancyGrid.empty((8, 8, 4), 0.1)
        grid.flat[np.arange(0, grid.size, 5)] = 100
        maps = {vid: encode_map(grid, MapMeta(vid, 1, 1.0)) for vid in (5, 7)}
        for vid, message in maps.items():
            assert d.sharing.received.offer(MessageSummary(vid, 1, len(message), grid.size), message)
        d._received_restored = True
        d.checkpoint()
        assert d.store.names() == ["peer-5", "peer-7"]
        d.sharing.received.max_vehicles = 2  # vehicle 9 arrives: 5, received first, is evicted ...
        message = encode_map(grid, MapMeta(9, 1, 1.0))
        assert d.sharing.received.offer(MessageSummary(9, 1, len(message), grid.size), message)
        assert {m.vehicle_id for m in d.sharing.received.all()} == {7, 9}
        d.checkpoint()
        assert d.store.names() == ["peer-7", "peer-9"]  # ... and its checkpoint with it
    finally:
        d.mapper.close()


def test_two_daemons_send_their_maps_as_deltas_and_hold_identical_maps(wd):
    """Daemon 1 maps (cells set in its grid, version bumped as a frame does) and publishes; daemon 2
    ends with daemon 1's map bit for bit after every version, most of them sent as deltas, and daemon 1
    charges its delta ledger to the memory budget."""
    from coopd.sharing import versions

    mav, share = port_block(4)
    key = swarm_key_file(wd)

    def config(vid: int, other: int):
        return from_dict({
            "vehicle": {"id": vid, "mavlink": f"udpin:127.0.0.1:{mav + vid}"},
            "camera": {"source": f"socket:{wd}/no-camera-{vid}.sock"},
            "sharing": {"listen_host": f"127.0.0.{vid}", "port": share + vid, "swarm_key_file": str(key),
                        "peers": [f"127.0.0.{other}:{share + other}"], "scan_period_s": 0.2},
            "daemon": {"state_dir": str(wd / f"state-{vid}"), "memory_mb": in_process_memory_mb(),
                       "control_socket": str(wd / f"control-{vid}.sock")},
        })

    one, two = Daemon(config(1, 2)), Daemon(config(2, 1))
    rng = np.random.default_rng(4)
    try:
        one.sharing.start()
        two.sharing.start()
        for step in range(8):
            with one.mapper.lock:  # a room mapped, then a few cells seen again each step
                x0 = 12 * step
                one.mapper.grid.set_keys(np.array([[x, y, z] for x in range(x0, x0 + 12)
                                                   for y in range(-10, 10) for z in range(0, 20)]),
                                         rng.choice(np.array([0, 0, 100], dtype=np.int8), size=12 * 20 * 20))
                one.mapper.grid.set_keys(rng.integers(0, x0 + 12, size=(5, 3)) - [0, 10, 0],
                                         np.full(5, 60, dtype=np.int8))
                one.mapper.version += 1
            one._publish_local()
            version = versions.compose(one.epoch, one.mapper.version)
            assert wait_until(lambda v=version: two.sharing.received.version(1) == v, 10)
            grid, _ = two.sharing.decode(1)
            assert grid.same_cells(one.mapper.grid)
        def peer():
            return next(p for p in one.sharing.stats()["peers"] if p["vehicle_id"] == 2)

        assert wait_until(lambda: peer()["maps_sent"] == 8, 5), peer()  # the last ack counted
        assert peer()["deltas_sent"] >= 6, peer()
        one._account_memory()
        assert one.budget.snapshot()["entries"]["sharing-deltas"] >= one._local_grid.size
    finally:
        for d in (one, two):
            d.sharing.stop()
            d.mapper.close()

"""kill -9 of a coopd that maps and checkpoints every second, then a restart: the map resumes from
the newest checkpoint (version and known cells at least those of the checkpoint), in the same map
frame, and no checkpoint is ever found corrupt. A few rounds by default, 20 in the slow run."""

import random
import shutil
import time

import pytest
from daemon_harness import Coopd, Sim, port_block, wait_until, workdir

from coopd.io import load_cmap


def _newest_checkpoint(state_dir):
    files = sorted(state_dir.glob("local.*.cmap"))
    return load_cmap(files[-1]) if files else None


def _crash_and_resume(rounds: int, port_index: int):
    wd = workdir("coopd-kill-")
    mav_port, share_port = port_block(port_index)
    rng = random.Random(rounds)
    d = Coopd(wd, "a", ["--vehicle-id", "1", "--mavlink", f"udpin:127.0.0.1:{mav_port}",
                        "--camera", f"socket:{Sim.camera_path(wd, 0)}", "--sharing-port", str(share_port),
                        "--checkpoint-period", "1", "--no-sharing"])
    sim = None
    history = []
    try:
        d.start()
        d.wait_running()
        sim = Sim(wd, mav_port, speed=3.0)
        origin = None
        for _ in range(rounds):
            s = wait_until(lambda: (s := d.status()) and s["frames"]["mapped"] >= 10
                           and s["checkpoint"]["saved"] >= 1 and s, 30)
            assert s, (d.last_error, d.log_text()[-2000:])
            origin = origin or s["link"]["map_origin_fc_enu"]
            assert s["link"]["map_origin_fc_enu"] == origin
            time.sleep(rng.uniform(0.0, 1.5))  # somewhere between checkpoints, maybe inside a write
            d.kill9()
            cp_grid, cp_meta = _newest_checkpoint(d.state_dir)
            cp_known = cp_grid.counts().known
            d.start()
            resumed = d.wait_running()
            history.append((cp_meta.version, cp_known, resumed["map"]["version"], resumed["map"]["known"]))
            assert resumed["map"]["version"] >= cp_meta.version, history
            assert resumed["map"]["known"] >= cp_known, history
            assert resumed["link"]["map_origin_fc_enu"] == origin
            assert resumed["checkpoint"]["set_aside"] == 0, resumed["checkpoint"]
        print({"rounds": rounds, "history (checkpoint version, known, resumed version, known)": history})
        assert not list(d.state_dir.glob("*.corrupt-*"))
        assert history[-1][1] > history[0][1]  # the map kept growing across the crashes
    finally:
        d.stop()
        if sim is not None:
            sim.stop()
    shutil.rmtree(wd, ignore_errors=True)


def test_kill9_and_restart_resumes_from_checkpoint():
    _crash_and_resume(rounds=2, port_index=2)


@pytest.mark.slow
def test_kill9_and_restart_20_times():
    _crash_and_resume(rounds=20, port_index=3)

"""The real coopd (coopd.daemon.main) under a real systemd, with the unit file unchanged: Debian booted
in systemd-nspawn as in test_nspawn_boot.py (whose container helpers this reuses). No vehicle is
attached, so the daemon waits for its FC and camera while systemd sees READY=1, STATUS= lines and
watchdog pings, and journald files each log line under its priority; a frozen daemon (SIGSTOP: no
thread runs) is killed by the watchdog and restarted; systemctl stop ends it cleanly within seconds."""

import json
import time

import pytest
from test_nspawn_boot import INNER_SRC, VENV, Container, _ensure_rootfs, _need_tools, coopctl, install_coopd

pytestmark = pytest.mark.slow

WRAPPER = f"""#!/bin/sh
# the real coopd from the bound source tree
export PYTHONPATH={INNER_SRC}
exec {VENV}/bin/python -m coopd.daemon.main "$@"
"""
# the container shares the host's network: ports of this engineer's range, loopback only
CONFIG = """
[vehicle]
mavlink = "udpin:127.0.0.1:15351"
[sharing]
listen_host = "127.0.0.1"
port = 15451
swarm_key_file = "/etc/coopd/swarm.key"
"""


def _wait(predicate, timeout):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(0.5)
    return predicate()


def test_real_coopd_under_systemd():
    _need_tools()
    _ensure_rootfs()
    c = Container()
    report = {}
    try:
        install_coopd(c, WRAPPER, CONFIG)

        t0 = time.monotonic()
        c.run("systemctl", "start", "coopd", timeout=150)  # Type=notify: returns after READY=1
        report["start_to_ready_s"] = round(time.monotonic() - t0, 1)
        r = coopctl(c, "status", "--json")
        assert r.returncode == 0, r.stderr
        status = json.loads(r.stdout)
        assert status["state"] == "running" and status["link"]["state"] == "connecting"
        nice = {t["role"]: t["applied"] for t in status["threads"] if t["thread"].startswith("coopd-")}
        assert nice["mavlink"] == -5 and nice["mapping"] == -3 and nice["merging"] == 10, nice
        report["nice"] = nice
        shown = c.show("StatusText", "MainPID", "NRestarts")
        assert shown["StatusText"].startswith("running: link connecting"), shown
        report["StatusText"] = shown["StatusText"]
        first_pid = int(shown["MainPID"])
        # journald stores each line's <N> priority: -p warning keeps the warnings (no camera
        # attached: "camera ... not reachable") and leaves the INFO lines out
        def journal(*args):
            return c.run("journalctl", "-u", "coopd", "--no-pager", "-o", "cat", f"_PID={first_pid}", *args,
                         check=False).stdout.splitlines()
        everything = _wait(lambda: (lines := journal()) and any(" not reachable (" in x for x in lines)
                           and lines, 30)
        warnings = journal("-p", "warning")
        assert any(x.startswith("INFO ") for x in everything), everything
        assert warnings and all(x.startswith(("WARNING ", "ERROR ", "CRITICAL ")) for x in warnings), warnings
        assert any(" not reachable (" in x for x in warnings), warnings
        assert not any(x.startswith("<") for x in everything), everything  # the prefix is parsed, not kept
        report["journal_lines"] = {"all": len(everything), "warning_and_above": len(warnings)}
        time.sleep(12)  # longer than WatchdogSec=10: the pings keep it alive
        assert c.show("NRestarts")["NRestarts"] == "0"
        assert c.run("systemctl", "is-active", "coopd", check=False).stdout.strip() == "active"

        # frozen daemon: no pings, systemd kills it after WatchdogSec and restarts it (Restart=on-failure)
        t0 = time.monotonic()
        c.run("systemctl", "kill", "--kill-whom=main", "--signal=SIGSTOP", "coopd")
        restarted = _wait(lambda: (s := c.show("MainPID", "NRestarts", "ActiveState"))["NRestarts"] == "1"
                          and s["ActiveState"] == "active" and int(s["MainPID"]) != first_pid and s, 90)
        assert restarted, c.show("MainPID", "NRestarts", "ActiveState", "Result")
        report["watchdog_restart_s"] = round(time.monotonic() - t0, 1)
        journal = c.run("journalctl", "-u", "coopd", "--no-pager", "-o", "cat", check=False).stdout
        assert "watchdog" in journal.lower()

        # clean stop: SIGTERM, STOPPING=1, exit 0 within seconds
        t0 = time.monotonic()
        c.run("systemctl", "stop", "coopd", timeout=30)
        report["stop_s"] = round(time.monotonic() - t0, 2)
        shown = c.show("ActiveState", "Result", "ExecMainStatus")
        assert shown["ActiveState"] == "inactive" and shown["Result"] == "success", shown
        assert report["stop_s"] < 5.0
        assert "stopped in" in c.run("journalctl", "-u", "coopd", "--no-pager", "-o", "cat",
                                     check=False).stdout
    finally:
        c.stop()
    print(json.dumps(report))

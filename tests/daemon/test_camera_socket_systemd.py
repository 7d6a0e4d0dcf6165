"""The camera socket as installed: under a real systemd (Debian in systemd-nspawn, as in
test_daemon_systemd.py), with the unit, sysusers and tmpfiles files unchanged and the default
camera source, the adapter printed in docs/camera-protocol.md runs as its own user in group coopd,
creates /run/coopd-camera/camera.sock, and the hardened daemon connects to it; the socket and the
connection survive a restart of coopd and of the driver."""

import json

import pytest
from test_daemon_systemd import WRAPPER, _wait
from test_nspawn_boot import VENV, Container, _ensure_rootfs, _need_tools, coopctl, install_coopd

from tests.docs_examples import adapter_example

pytestmark = pytest.mark.slow

CONFIG = """
[vehicle]
mavlink = "udpin:127.0.0.1:15352"
[sharing]
enabled = false
swarm_key_file = "/etc/coopd/swarm.key"
"""
SOCKET = "/run/coopd-camera/camera.sock"


def _camera(c: Container) -> dict | None:
    r = coopctl(c, "status", "--json")
    return json.loads(r.stdout)["camera"] if r.returncode == 0 else None


def test_a_driver_as_another_user_serves_coopd_through_the_default_socket_across_restarts():
    _need_tools()
    _ensure_rootfs()
    c = Container()
    report = {}
    try:
        install_coopd(c, WRAPPER, CONFIG)
        c.run("useradd", "--system", "--no-create-home", "camdrv")
        c.run("chmod", "0711", "/root")  # (volatile overlay) lets camdrv reach the pyenv Python under /root
        c.write("/opt/camera-adapter.py", adapter_example())
        report["dir"] = c.run("stat", "-c", "%a %U %G", "/run/coopd-camera").stdout.split()
        assert report["dir"] == ["3770", "root", "coopd"]
        c.run("systemd-run", "--unit=camdrv", "-p", "User=camdrv", "-p", "SupplementaryGroups=coopd",
              "-p", "UMask=0007", f"{VENV}/bin/python", "/opt/camera-adapter.py")
        assert _wait(lambda: c.run("test", "-S", SOCKET, check=False).returncode == 0, 30), \
            c.run("journalctl", "-u", "camdrv", "--no-pager", "-o", "cat", check=False).stdout[-2000:]
        report["socket"] = c.run("stat", "-c", "%a %U %G %i", SOCKET).stdout.split()
        assert report["socket"][1:3] == ["camdrv", "coopd"]

        c.run("systemctl", "start", "coopd", timeout=150)
        cam = _wait(lambda: (s := _camera(c)) and s["connected"] and s["counters"].get("dropped_no_fc_clock")
                    and s, 30)
        assert cam, (_camera(c), _journal(c))  # frames arrive; without an FC they wait for its clock
        assert cam["source"] == "socket:" + SOCKET

        c.run("systemctl", "restart", "coopd", timeout=150)  # the RuntimeDirectory goes, the socket stays
        assert c.run("stat", "-c", "%a %U %G %i", SOCKET).stdout.split() == report["socket"]
        assert _wait(lambda: (s := _camera(c)) and s["connected"], 30), (_camera(c), _journal(c))

        c.run("systemctl", "stop", "camdrv")  # the driver restarts (as a new transient unit)
        c.run("systemd-run", "--unit=camdrv2", "-p", "User=camdrv", "-p", "SupplementaryGroups=coopd",
              "-p", "UMask=0007", f"{VENV}/bin/python", "/opt/camera-adapter.py")
        cam = _wait(lambda: (s := _camera(c)) and s["reconnects"] >= 1 and s["connected"] and s, 30)
        assert cam, (_camera(c), _journal(c))
        report["counters"] = cam["counters"]
    finally:
        c.stop()
    print(json.dumps(report))


def _journal(c: Container) -> str:
    return c.run("journalctl", "-u", "coopd", "--no-pager", "-o", "cat", check=False).stdout[-3000:]

"""The default camera socket: in /run/coopd-camera (systemd/coopd.tmpfiles), not coopd's
RuntimeDirectory, so a driver running as another user in group coopd can create it and it outlives
coopd restarts. Shown with systemd-tmpfiles --root on a scratch tree and processes running as
three other users (needs root to switch users; no systemd needed)."""

import os
import shutil
import subprocess
import tempfile
from pathlib import Path

import pytest

from coopd.camera.socket_source import CAMERA_SOCKET_DIR
from coopd.daemon.config import Config
from tests.proof import skip_proof

ROOT = Path(__file__).resolve().parents[2]
TMPFILES = ROOT / "systemd" / "coopd.tmpfiles"
COOPD_GID, DRIVER_UID, OUTSIDER_UID = 64990, 64001, 64002
SYSTEM_PYTHON = shutil.which("python3", path="/usr/bin:/bin")
"""The test users cannot read the project's Python (under /root); their scripts need only the stdlib."""


def tmpfiles_entries() -> list[list[str]]:
    return [ln.split() for ln in TMPFILES.read_text().splitlines() if ln.strip() and not ln.startswith("#")]


def test_the_default_camera_socket_lives_in_the_tmpfiles_directory_not_the_runtime_directory():
    source = Config.defaults().camera.source
    assert source == f"socket:{CAMERA_SOCKET_DIR}/camera.sock"
    unit = (ROOT / "systemd" / "coopd.service").read_text()
    runtime = [d for ln in unit.splitlines() if ln.startswith("RuntimeDirectory=") for d in ln[17:].split()]
    assert runtime and CAMERA_SOCKET_DIR not in ["/run/" + d for d in runtime]  # those are wiped on restart
    assert tmpfiles_entries() == [["d", CAMERA_SOCKET_DIR, "3770", "root", "coopd", "-"]]
    sysusers = (ROOT / "systemd" / "coopd.sysusers").read_text().splitlines()
    assert any(ln.split()[:2] == ["g", "coopd"] for ln in sysusers if ln.strip())


def _as(uid: int, gid: int, groups: list[int], code: str, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [SYSTEM_PYTHON, "-c", code, *args], user=uid, group=gid, extra_groups=groups,
        capture_output=True, text=True, timeout=30,
    )


DRIVER = """
import os, socket, sys
os.umask(0o007)
s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
s.bind(sys.argv[1]); s.listen(1); print("listening", flush=True)
c, _ = s.accept(); c.sendall(b"frame"); c.close()
"""
READER = """
import socket, sys
s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
s.settimeout(10); s.connect(sys.argv[1]); print(s.recv(16).decode())
"""
BINDER = """
import socket, sys
try:
    socket.socket(socket.AF_UNIX, socket.SOCK_STREAM).bind(sys.argv[1])
except PermissionError:
    print("denied")
"""


def test_a_driver_in_group_coopd_creates_the_socket_and_coopd_connects():
    if os.geteuid() != 0:
        pytest.skip("needs root to run processes as other users")
    tool = shutil.which("systemd-tmpfiles")
    if tool is None or SYSTEM_PYTHON is None:
        skip_proof("systemd-tmpfiles or /usr/bin/python3 not installed")
    scratch = Path(tempfile.mkdtemp(prefix="coopd-tmpfiles-"))
    try:
        scratch.chmod(0o755)  # the test users must reach what is inside
        (scratch / "etc").mkdir()
        (scratch / "etc" / "passwd").write_text("root:x:0:0::/root:/bin/sh\n")
        (scratch / "etc" / "group").write_text(f"root:x:0:\ncoopd:x:{COOPD_GID}:\n")
        r = subprocess.run([tool, "--create", f"--root={scratch}", str(TMPFILES)], capture_output=True,
                           text=True, timeout=60)
        assert r.returncode == 0, r.stderr
        directory = scratch / CAMERA_SOCKET_DIR.lstrip("/")
        st = directory.stat()
        assert (oct(st.st_mode & 0o7777), st.st_uid, st.st_gid) == ("0o3770", 0, COOPD_GID)
        os.chmod(scratch / "run", 0o755)
        path = str(directory / "camera.sock")

        # the driver: its own user, in group coopd
        driver = subprocess.Popen([SYSTEM_PYTHON, "-c", DRIVER, path], user=DRIVER_UID, group=DRIVER_UID,
                                  extra_groups=[COOPD_GID], stdout=subprocess.PIPE, text=True)
        try:
            assert driver.stdout.readline().strip() == "listening"
            sock = os.stat(path)
            assert sock.st_gid == COOPD_GID and sock.st_mode & 0o067 == 0o060  # setgid dir, umask 0007
            # coopd: user and group coopd
            reader = _as(COOPD_GID, COOPD_GID, [], READER, path)
            assert reader.stdout.strip() == "frame", reader.stderr
            assert driver.wait(timeout=10) == 0
        finally:
            driver.kill()
            driver.wait(timeout=10)
        # a user outside group coopd can neither create a socket there nor replace the driver's
        outsider = _as(OUTSIDER_UID, OUTSIDER_UID, [], BINDER, str(directory / "other.sock"))
        assert outsider.stdout.strip() == "denied", outsider.stderr
        # another member of group coopd cannot remove the driver's socket (sticky bit)
        unlink = f"import os\ntry:\n os.unlink({path!r})\nexcept PermissionError:\n print('denied')"
        remover = _as(COOPD_GID, COOPD_GID, [], unlink)
        assert remover.stdout.strip() == "denied", remover.stderr
    finally:
        shutil.rmtree(scratch, ignore_errors=True)

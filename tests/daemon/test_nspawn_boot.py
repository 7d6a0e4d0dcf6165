"""The unit under a real systemd: boot Debian in systemd-nspawn, install unit and config, start.

Slow (a boot, ~30-60 s; the first run also debootstraps the tree, ~2 min with network).
Needs root, systemd-nspawn (Debian systemd-container) and, for the first run, debootstrap. The
debootstrapped tree is cached outside the repo ($COOPD_NSPAWN_ROOT, default
/var/cache/coopd-nspawn/bookworm) and booted with --volatile=overlay, so it stays clean.

The project's venv, its Python (pyenv, under /root) and this source tree are bound in read-only.
The unit is installed unchanged plus one drop-in: ProtectHome=tmpfs with the pyenv directory
bound back in (ProtectHome=yes would hide the test's Python, which lives under /root).
/usr/local/bin/coopd is a two-line wrapper around tests/daemon/standin_service.py, which runs the
real service pieces (coopd/daemon/main.py, the full daemon, is not written yet).

Shown: READY (systemctl start returns, unit active), coopctl status inside, permission denied
for a user outside group coopd, clean SIGTERM stop with a checkpoint, resume from it, and the
watchdog killing and restarting a daemon whose main loop hangs.
"""

import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest

from coopd.cli.key_commands import key_file_text
from tests.proof import skip_proof

pytestmark = pytest.mark.slow

SRC = Path(__file__).resolve().parents[2]
ROOTFS = Path(os.environ.get("COOPD_NSPAWN_ROOT", "/var/cache/coopd-nspawn/bookworm"))
VENV = Path(sys.prefix)
PYHOME = Path(os.path.realpath(sys.executable)).parents[1]
INNER_SRC = "/opt/coopd-src"

WRAPPER = f"""#!/bin/sh
# test stand-in for the coopd executable (see tests/daemon/standin_service.py)
export PYTHONPATH={INNER_SRC}
exec {VENV}/bin/python {INNER_SRC}/tests/daemon/standin_service.py "$@"
"""
DROPIN = f"""[Service]
# The test's Python lives under /root (pyenv): hide /root as the unit does, then bind it back.
ProtectHome=tmpfs
BindReadOnlyPaths={PYHOME}
"""


def _need_tools():
    if os.geteuid() != 0:
        pytest.skip("needs root (systemd-nspawn)")
    for tool in ("systemd-nspawn", "nsenter"):
        if shutil.which(tool) is None:
            skip_proof(f"{tool} not installed (Debian packages systemd-container, util-linux)")


def _ensure_rootfs():
    if (ROOTFS / "usr/lib/systemd/systemd").exists():
        return
    if shutil.which("debootstrap") is None:
        skip_proof(f"no cached tree at {ROOTFS} and debootstrap is not installed")
    tmp = ROOTFS.with_name(ROOTFS.name + ".tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.parent.mkdir(parents=True, exist_ok=True)
    r = subprocess.run(
        [
            "debootstrap",
            "--variant=minbase",
            "--include=systemd,systemd-sysv,dbus",
            "bookworm",
            str(tmp),
            "http://deb.debian.org/debian",
        ],
        capture_output=True,
        text=True,
        timeout=1200,
    )
    if r.returncode != 0:
        skip_proof(f"debootstrap failed (network?): {r.stderr.strip()[-300:]}")
    tmp.rename(ROOTFS)


class Container:
    def __init__(self):
        self.proc = subprocess.Popen(
            [
                "systemd-nspawn",
                "-D",
                str(ROOTFS),
                "--volatile=overlay",
                "--register=no",
                "--keep-unit",
                "-b",
                "--console=pipe",
                "-M",
                "coopdtest",
                f"--bind-ro={VENV}",
                f"--bind-ro={PYHOME}",
                f"--bind-ro={SRC}:{INNER_SRC}",
            ],
            stdin=subprocess.DEVNULL,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
        )
        self.leader = None
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and self.proc.poll() is None:
            children = Path(f"/proc/{self.proc.pid}/task/{self.proc.pid}/children")
            pids = children.read_text().split() if children.exists() else []
            if pids:
                self.leader = int(pids[0])
                r = self.run("systemctl", "is-system-running", "--wait", check=False, timeout=60)
                if r.stdout.strip() in ("running", "degraded"):
                    return
            time.sleep(0.2)
        raise AssertionError(f"container did not boot: {self.output()}")

    def run(self, *cmd, check=True, timeout=60, input=None, user=None):
        prefix = ["nsenter", "-t", str(self.leader), "-a"]
        if user is not None:
            prefix += ["setpriv", f"--reuid={user}", f"--regid={user}", "--clear-groups"]
        r = subprocess.run(prefix + list(cmd), capture_output=True, text=True, timeout=timeout, input=input)
        if check and r.returncode != 0:
            raise AssertionError(f"{cmd} failed ({r.returncode}): {r.stdout}{r.stderr}")
        return r

    def write(self, path: str, text: str, mode: str = "0644"):
        self.run(
            "sh", "-c", f'mkdir -p "$(dirname {path})" && cat > {path} && chmod {mode} {path}', input=text
        )

    def show(self, *props) -> dict:
        out = self.run("systemctl", "show", "coopd", *(f"-p{p}" for p in props)).stdout
        return dict(line.split("=", 1) for line in out.splitlines() if "=" in line)

    def output(self) -> str:
        return ""

    def stop(self):
        if self.proc.poll() is None:
            self.proc.terminate()  # nspawn asks the container's systemd to shut down
            try:
                self.proc.wait(30)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()


def install_coopd(c: Container, wrapper: str, config: str) -> None:
    """coopd installed in container c as docs/operations.md says (wrapper as /usr/local/bin/coopd, the
    config, a swarm key, the unit unchanged plus the test's drop-in, sysusers and tmpfiles entries)."""
    c.write("/usr/local/bin/coopd", wrapper, "0755")
    c.write("/etc/coopd/coopd.toml", config)
    c.write("/etc/coopd/swarm.key", key_file_text(os.urandom(32)), "0600")
    c.write("/etc/systemd/system/coopd.service", (SRC / "systemd/coopd.service").read_text())
    c.write("/etc/systemd/system/coopd.service.d/test-python-under-root.conf", DROPIN)
    c.write("/etc/sysusers.d/coopd.conf", (SRC / "systemd/coopd.sysusers").read_text())
    c.run("systemd-sysusers")
    c.write("/etc/tmpfiles.d/coopd.conf", (SRC / "systemd/coopd.tmpfiles").read_text())
    c.run("systemd-tmpfiles", "--create", "/etc/tmpfiles.d/coopd.conf")
    c.run("chown", "coopd:coopd", "/etc/coopd/swarm.key")
    c.run("systemctl", "daemon-reload")


def coopctl(c: Container, *args, user=None):
    # NUMBA_CACHE_DIR: coopctl imports coopd.io (map tools) whose numba kernels are cached; a user
    # without a home directory (nobody) and a read-only source tree leaves numba nowhere to cache.
    return c.run(
        "env",
        f"PYTHONPATH={INNER_SRC}",
        f"NUMBA_CACHE_DIR=/tmp/coopctl-numba-{user}",
        f"{VENV}/bin/python",
        "-m",
        "coopd.cli.coopctl",
        *args,
        check=False,
        user=user,
    )


def test_unit_under_real_systemd(capsys):
    _need_tools()
    _ensure_rootfs()
    c = Container()
    report = []
    try:
        # the shipped config with the one step every install adds: a swarm key (docs/operations.md)
        install_coopd(c, WRAPPER, (SRC / "etc/coopd.toml").read_text().replace(
            'swarm_key_file = ""', 'swarm_key_file = "/etc/coopd/swarm.key"'))

        t0 = time.monotonic()
        c.run("systemctl", "start", "coopd", timeout=150)  # Type=notify: returns after READY=1
        report.append(f"start -> active (READY=1) in {time.monotonic() - t0:.1f} s")
        assert c.run("systemctl", "is-active", "coopd", check=False).stdout.strip() == "active"

        r = coopctl(c, "status", "--json")
        assert r.returncode == 0, r.stderr
        status = json.loads(r.stdout)
        first_pid = status["pid"]
        assert status["vehicle_id"] == 1 and status["state"] == "running"
        assert status["memory"]["rss_bytes"] < status["memory"]["budget_bytes"]
        nice = {t["role"]: t["applied"] for t in status["threads"]}
        assert nice == {"mapping": -3, "control": 0}  # CAP_SYS_NICE from the unit
        report.append(
            f"coopctl status: pid {first_pid}, RSS {status['memory']['rss_bytes'] / 2**20:.0f} MiB "
            f"of {status['memory']['budget_bytes'] / 2**20:.0f} MiB, nice {nice}"
        )
        table = coopctl(c, "status")
        assert table.returncode == 0 and "running" in table.stdout
        sock = c.run("stat", "-c", "%a %U %G", "/run/coopd/control.sock").stdout.split()
        assert sock == ["660", "coopd", "coopd"], sock
        c.run("chmod", "0711", "/root")  # (volatile overlay) lets nobody reach the pyenv Python under /root
        denied = coopctl(c, "status", user=65534)
        assert denied.returncode == 1 and "permission denied" in denied.stderr, denied.stderr

        t0 = time.monotonic()
        c.run("systemctl", "stop", "coopd", timeout=60)
        stop_s = time.monotonic() - t0
        assert stop_s < 5
        files = c.run("ls", "/var/lib/coopd").stdout.split()
        assert "local.0000000001.cmap" in files
        report.append(f"SIGTERM stop in {stop_s:.2f} s, checkpoint {files}")

        c.run("systemctl", "start", "coopd", timeout=150)
        status = json.loads(coopctl(c, "status", "--json").stdout)
        assert status["resumed_from"] == "/var/lib/coopd/local.0000000001.cmap"
        assert status["map"]["version"] == 1

        before = c.show("MainPID", "NRestarts")
        c.run(
            "env",
            f"PYTHONPATH={INNER_SRC}",
            f"{VENV}/bin/python",
            "-c",
            "from coopd.daemon import control; print(control.request('/run/coopd/control.sock', 'hang'))",
        )
        t0 = time.monotonic()
        deadline = t0 + 60
        now = before
        while time.monotonic() < deadline:
            now = c.show("MainPID", "NRestarts", "ActiveState")
            if (
                int(now["NRestarts"]) > int(before["NRestarts"])
                and now["ActiveState"] == "active"
                and now["MainPID"] not in ("0", before["MainPID"])
            ):
                break
            time.sleep(0.5)
        restart_s = time.monotonic() - t0
        assert int(now["NRestarts"]) == int(before["NRestarts"]) + 1, now
        journal = c.run("journalctl", "-u", "coopd", "--no-pager", "-o", "cat").stdout
        assert "Watchdog timeout" in journal, journal[-2000:]
        status = json.loads(coopctl(c, "status", "--json").stdout)
        assert status["pid"] == int(now["MainPID"]) != int(before["MainPID"])
        report.append(
            f"hung main loop: watchdog restart after {restart_s:.1f} s "
            f"(pid {before['MainPID']} -> {now['MainPID']}, NRestarts {now['NRestarts']})"
        )
    finally:
        c.stop()
        with capsys.disabled():
            print("\n" + "\n".join(report))

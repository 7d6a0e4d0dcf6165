"""coopd installed the way a user installs it, under a real systemd: Debian bookworm booted in
systemd-nspawn, the built wheel installed with scripts/install, the unit unchanged.

The wheel is built from this checkout (`pip wheel --no-deps`), its dependencies are gathered as
wheels into a wheelhouse on the host (cached next to the tree), and inside the container the
documented command runs offline against them: `scripts/install --wheel FILE` with PIP_NO_INDEX and
PIP_FIND_LINKS, as on a drone without internet. Nothing of the host's Python is visible in the
container: it installs with Debian's python3 into /opt/coopd, compiles the kernels into the unit's
cache directory, and the first `systemctl start coopd` is timed (printed; the goal is READY in
10 s on 2 cores). Then: coopctl status answers, a user outside group coopd is refused, a frozen
daemon is killed by the watchdog and restarted, `systemctl stop` ends it cleanly within seconds.

Slow: a boot, the install (about 1-3 min, most of it the kernels' compilation) and the checks.
Needs root, systemd-nspawn (Debian systemd-container) and, the first time, debootstrap and network:
the tree (debootstrapped with python3 and python3-venv) is cached outside the repo in
$COOPD_NSPAWN_ROOT (default /var/cache/coopd-nspawn/bookworm-python3), the wheelhouse beside it,
and the tree is booted with --volatile=overlay and --private-network, so it stays clean and the
daemon's ports are the container's own.
"""

import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest

from coopd.cli.output import UNREACHABLE
from tests.proof import skip_proof

pytestmark = [pytest.mark.slow, pytest.mark.timeout(1800)]  # a boot, an install, the checks

SRC = Path(__file__).resolve().parents[2]
ROOTFS = Path(os.environ.get("COOPD_NSPAWN_ROOT", "/var/cache/coopd-nspawn/bookworm-python3"))
WHEELHOUSE = ROOTFS.with_name(ROOTFS.name + "-wheels")
INNER_SRC = "/srv/coopd-src"
INNER_WHEELHOUSE = "/srv/wheelhouse"
INNER_DIST = "/srv/dist"
PATH = "/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin"
DEBIAN_PACKAGES = "systemd,systemd-sysv,dbus,python3,python3-venv"


def _need_tools():
    if os.geteuid() != 0:
        pytest.skip("needs root (systemd-nspawn)")
    for tool in ("systemd-nspawn", "nsenter"):
        if shutil.which(tool) is None:
            skip_proof(f"{tool} not installed (Debian packages systemd-container, util-linux)")


def _ensure_rootfs():
    if (ROOTFS / "usr/lib/systemd/systemd").exists():
        if not (ROOTFS / "usr/lib/python3.11/ensurepip").is_dir():
            skip_proof(f"the tree at {ROOTFS} has no python3-venv: remove it (it is debootstrapped again)")
        return
    if shutil.which("debootstrap") is None:
        skip_proof(f"no cached tree at {ROOTFS} and debootstrap is not installed")
    tmp = ROOTFS.with_name(ROOTFS.name + ".tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.parent.mkdir(parents=True, exist_ok=True)
    r = subprocess.run(
        ["debootstrap", "--variant=minbase", f"--include={DEBIAN_PACKAGES}", "bookworm", str(tmp),
         "http://deb.debian.org/debian"],
        capture_output=True, text=True, timeout=1800,
    )
    if r.returncode != 0:
        skip_proof(f"debootstrap failed (network?): {r.stderr.strip()[-300:]}")
    tmp.rename(ROOTFS)


def build_wheel(dist: Path) -> Path:
    """The coopd wheel of this checkout, as `pip wheel --no-deps` builds it."""
    r = subprocess.run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "-w", str(dist), str(SRC)],
                       capture_output=True, text=True, timeout=900)
    assert r.returncode == 0, r.stderr[-2000:]
    (wheel,) = dist.glob("coopd-*.whl")
    return wheel


def fill_wheelhouse(wheel: Path) -> None:
    """Every dependency of the wheel (no extras) as a wheel in WHEELHOUSE: offline when the cache
    already holds them, else from the package index."""
    WHEELHOUSE.mkdir(parents=True, exist_ok=True)
    cmd = [sys.executable, "-m", "pip", "wheel", "-q", "-w", str(WHEELHOUSE), "--find-links", str(WHEELHOUSE),
           str(wheel)]
    r = subprocess.run(cmd + ["--no-index"], capture_output=True, text=True, timeout=900)
    if r.returncode != 0:
        r = subprocess.run(cmd, capture_output=True, text=True, timeout=1800)
        if r.returncode != 0:
            skip_proof(f"could not gather the dependencies' wheels (network?): {r.stderr.strip()[-300:]}")
    for own in WHEELHOUSE.glob("coopd-*.whl"):
        own.unlink()  # the container installs the wheel under test, named by path


class Container:
    def __init__(self, dist: Path):
        self.proc = subprocess.Popen(
            [
                "systemd-nspawn", "-D", str(ROOTFS), "--volatile=overlay", "--register=no", "--keep-unit",
                "--private-network", "-b", "--console=pipe", "-M", "coopdtest",
                f"--bind-ro={SRC}:{INNER_SRC}",
                f"--bind-ro={WHEELHOUSE}:{INNER_WHEELHOUSE}",
                f"--bind-ro={dist}:{INNER_DIST}",
            ],
            stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
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
        raise AssertionError("container did not boot")

    def run(self, *cmd, check=True, timeout=60, input=None, user=None):
        """cmd inside the container with a root shell's environment (none of the test's)."""
        prefix = ["nsenter", "-t", str(self.leader), "-a"]
        if user is not None:
            prefix += ["setpriv", f"--reuid={user}", f"--regid={user}", "--clear-groups"]
        prefix += ["env", "-i", f"PATH={PATH}", "LANG=C.UTF-8"]
        r = subprocess.run(prefix + list(cmd), capture_output=True, text=True, timeout=timeout, input=input)
        if check and r.returncode != 0:
            raise AssertionError(f"{cmd} failed ({r.returncode}): {r.stdout}{r.stderr}")
        return r

    def write(self, path: str, text: str, mode: str = "0644"):
        script = f'mkdir -p "$(dirname {path})" && cat > {path} && chmod {mode} {path}'
        self.run("sh", "-c", script, input=text)

    def show(self, *props) -> dict:
        out = self.run("systemctl", "show", "coopd", *(f"-p{p}" for p in props)).stdout
        return dict(line.split("=", 1) for line in out.splitlines() if "=" in line)

    def journal(self) -> str:
        return self.run("journalctl", "-u", "coopd", "--no-pager", "-o", "cat", check=False).stdout

    def stop(self):
        if self.proc.poll() is None:
            self.proc.terminate()  # nspawn asks the container's systemd to shut down
            try:
                self.proc.wait(30)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()


def coopctl(c: Container, *args, user=None):
    return c.run("coopctl", *args, check=False, user=user)


def _wait(predicate, timeout):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(0.5)
    return predicate()


@pytest.fixture(scope="module")
def installed(tmp_path_factory):
    """A booted container with coopd installed by scripts/install and configured as
    docs/operations.md says (a swarm key); not started yet. Yields (container, report)."""
    _need_tools()
    _ensure_rootfs()
    dist = tmp_path_factory.mktemp("dist")
    wheel = build_wheel(dist)
    fill_wheelhouse(wheel)
    c = Container(dist)
    report = {}
    try:
        t0 = time.monotonic()
        offline = ("PIP_NO_INDEX=1", f"PIP_FIND_LINKS={INNER_WHEELHOUSE}")
        r = c.run("env", *offline, f"{INNER_SRC}/scripts/install", "--wheel", f"{INNER_DIST}/{wheel.name}",
                  timeout=1800)
        report["install_s"] = round(time.monotonic() - t0, 1)
        report["install_output"] = [ln for ln in r.stderr.splitlines() + r.stdout.splitlines()
                                    if "warm-up" in ln or ln.startswith("install: coopd is installed")]
        assert c.run("readlink", "/usr/local/bin/coopctl").stdout.strip() == "/opt/coopd/bin/coopctl"
        assert "ExecStart=/opt/coopd/bin/coopd --config /etc/coopd/coopd.toml" in c.run(
            "cat", "/etc/systemd/system/coopd.service").stdout
        c.run("coopctl", "key", "generate", "--out", "/etc/coopd/swarm.key")
        c.run("chown", "coopd:coopd", "/etc/coopd/swarm.key")
        c.run("sed", "-i", 's|^swarm_key_file = ""|swarm_key_file = "/etc/coopd/swarm.key"|',
              "/etc/coopd/coopd.toml")
        yield c, report
    finally:
        c.stop()
        print("\n" + json.dumps(report, indent=1))


def test_install_and_first_start(installed):
    c, report = installed
    # the kernels were compiled at install time, into the unit's cache directory, by the daemon's user
    assert "swarm.key" in c.run("grep", "^swarm_key_file", "/etc/coopd/coopd.toml").stdout
    assert c.run("stat", "-c", "%U %G %a", "/var/cache/coopd").stdout.split() == ["coopd", "coopd", "750"]
    cached = c.run("find", "/var/cache/coopd/numba", "-name", "*.nbi").stdout.split()
    assert len(cached) > 5, cached

    t0 = time.monotonic()
    c.run("systemctl", "start", "coopd", timeout=150)  # Type=notify: returns after READY=1
    report["first_start_to_ready_s"] = round(time.monotonic() - t0, 1)
    report["kernels_ready"] = [ln for ln in c.journal().splitlines() if "kernels ready" in ln]
    assert c.run("systemctl", "is-active", "coopd", check=False).stdout.strip() == "active"

    r = coopctl(c, "status", "--json")
    assert r.returncode == 0, r.stderr
    status = json.loads(r.stdout)
    assert status["vehicle_id"] == 1 and status["state"] == "running"
    assert status["link"]["state"] == "connecting"  # no flight controller in the container
    assert status["memory"]["rss_bytes"] < status["memory"]["budget_bytes"]
    report["rss_mib"] = round(status["memory"]["rss_bytes"] / 2**20)
    table = coopctl(c, "status")
    assert table.returncode == 0 and "running" in table.stdout
    sock = c.run("stat", "-c", "%a %U %G", "/run/coopd/control.sock").stdout.split()
    assert sock == ["660", "coopd", "coopd"], sock
    denied = coopctl(c, "status", user=65534)
    assert denied.returncode == UNREACHABLE.code and "permission denied" in denied.stderr, denied.stderr

    # clean stop; the state directory was writable (ProtectSystem=strict leaves only the unit's own)
    t0 = time.monotonic()
    c.run("systemctl", "stop", "coopd", timeout=60)
    report["stop_s"] = round(time.monotonic() - t0, 2)
    shown = c.show("ActiveState", "Result")
    assert shown["ActiveState"] == "inactive" and shown["Result"] == "success", shown
    assert report["stop_s"] < 5
    files = c.run("ls", "/var/lib/coopd").stdout.split()
    assert "version-reserve.json" in files, files  # an empty map (no vehicle) has no checkpoint to write
    assert "stopped in" in c.journal()
    # after the install's warm-up and a run of the daemon (UMask=0027): the kernel cache is code the
    # daemon loads, writable by its user only
    writable = c.run("find", "/var/cache/coopd", "-perm", "/022").stdout.split()
    assert writable == [], writable


def test_watchdog_restarts_a_frozen_daemon_and_stop_is_clean(installed):
    c, report = installed
    c.run("systemctl", "start", "coopd", timeout=150)
    r = coopctl(c, "status", "--json")
    assert r.returncode == 0, r.stderr
    status = json.loads(r.stdout)
    nice = {t["role"]: t["applied"] for t in status["threads"] if t["thread"].startswith("coopd-")}
    assert nice["mavlink"] == -5 and nice["mapping"] == -3 and nice["merging"] == 10, nice  # CAP_SYS_NICE
    report["nice"] = nice
    shown = c.show("StatusText", "MainPID", "NRestarts")
    assert shown["StatusText"].startswith("running: link connecting"), shown
    first_pid, restarts = int(shown["MainPID"]), int(shown["NRestarts"])

    # journald files each line under its <N> priority: -p warning keeps the warnings (no camera
    # attached: "camera ... not reachable") and leaves the INFO lines out
    def journal(*args):
        return c.run("journalctl", "-u", "coopd", "--no-pager", "-o", "cat", f"_PID={first_pid}", *args,
                     check=False).stdout.splitlines()

    everything = _wait(lambda: (lines := journal()) and any(" not reachable (" in x for x in lines) and lines,
                       30)
    warnings = journal("-p", "warning")
    assert any(x.startswith("INFO ") for x in everything), everything
    assert warnings and all(x.startswith(("WARNING ", "ERROR ", "CRITICAL ")) for x in warnings), warnings
    assert any(" not reachable (" in x for x in warnings), warnings
    assert not any(x.startswith("<") for x in everything), everything  # the prefix is parsed, not kept
    report["journal_lines"] = {"all": len(everything), "warning_and_above": len(warnings)}
    time.sleep(12)  # longer than WatchdogSec=10: the pings keep it alive
    assert int(c.show("NRestarts")["NRestarts"]) == restarts
    assert c.run("systemctl", "is-active", "coopd", check=False).stdout.strip() == "active"

    # frozen daemon: no pings, systemd kills it after WatchdogSec and restarts it (Restart=on-failure)
    t0 = time.monotonic()
    c.run("systemctl", "kill", "--kill-whom=main", "--signal=SIGSTOP", "coopd")
    restarted = _wait(lambda: (s := c.show("MainPID", "NRestarts", "ActiveState"))["NRestarts"]
                      == str(restarts + 1) and s["ActiveState"] == "active" and int(s["MainPID"]) != first_pid
                      and s, 90)
    assert restarted, c.show("MainPID", "NRestarts", "ActiveState", "Result")
    report["watchdog_restart_s"] = round(time.monotonic() - t0, 1)
    assert "watchdog" in c.journal().lower()

    # clean stop: SIGTERM, STOPPING=1, exit 0 within seconds
    t0 = time.monotonic()
    c.run("systemctl", "stop", "coopd", timeout=30)
    stop_s = round(time.monotonic() - t0, 2)
    shown = c.show("ActiveState", "Result", "ExecMainStatus")
    assert shown["ActiveState"] == "inactive" and shown["Result"] == "success", shown
    assert stop_s < 5.0
    assert "stopped in" in c.journal()


CAMERA_SOCKET = "/run/coopd-camera/camera.sock"


def _camera(c: Container) -> dict | None:
    r = coopctl(c, "status", "--json")
    return json.loads(r.stdout)["camera"] if r.returncode == 0 else None


def test_a_camera_driver_as_another_user_serves_coopd_through_the_default_socket_across_restarts(installed):
    """The camera socket directory the install creates (/run/coopd-camera, root:coopd 3770) lets a
    driver running as its own user in group coopd create the socket; coopd connects, and socket and
    connection survive restarts of coopd and of the driver. The driver is the documented adapter."""
    from tests.docs_examples import adapter_example

    c, report = installed
    c.run("useradd", "--system", "--no-create-home", "camdrv")
    c.write("/opt/camera-adapter.py", adapter_example())
    assert c.run("stat", "-c", "%a %U %G", "/run/coopd-camera").stdout.split() == ["3770", "root", "coopd"]
    driver = ("-p", "User=camdrv", "-p", "SupplementaryGroups=coopd", "-p", "UMask=0007",
              "/opt/coopd/bin/python", "/opt/camera-adapter.py")
    c.run("systemd-run", "--unit=camdrv", *driver)
    assert _wait(lambda: c.run("test", "-S", CAMERA_SOCKET, check=False).returncode == 0, 30), \
        c.run("journalctl", "-u", "camdrv", "--no-pager", "-o", "cat", check=False).stdout[-2000:]
    socket_stat = c.run("stat", "-c", "%a %U %G %i", CAMERA_SOCKET).stdout.split()
    assert socket_stat[1:3] == ["camdrv", "coopd"]

    c.run("systemctl", "start", "coopd", timeout=150)
    cam = _wait(lambda: (s := _camera(c)) and s["connected"] and s["counters"].get("dropped_no_fc_clock")
                and s, 30)
    assert cam, (_camera(c), c.journal()[-3000:])  # frames arrive; without an FC they wait for its clock
    assert cam["source"] == "socket:" + CAMERA_SOCKET

    c.run("systemctl", "restart", "coopd", timeout=150)  # the RuntimeDirectory goes, the socket stays
    assert c.run("stat", "-c", "%a %U %G %i", CAMERA_SOCKET).stdout.split() == socket_stat
    assert _wait(lambda: (s := _camera(c)) and s["connected"], 30), (_camera(c), c.journal()[-3000:])

    c.run("systemctl", "stop", "camdrv")  # the driver restarts (as a new transient unit)
    c.run("systemd-run", "--unit=camdrv2", *driver)
    cam = _wait(lambda: (s := _camera(c)) and s["reconnects"] >= 1 and s["connected"] and s, 30)
    assert cam, (_camera(c), c.journal()[-3000:])
    report["camera_counters"] = cam["counters"]
    c.run("systemctl", "stop", "coopd", "camdrv2", timeout=60)

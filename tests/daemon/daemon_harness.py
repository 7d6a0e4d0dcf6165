"""Helpers for the coopd process tests: firmware_sim and coopd as subprocesses on loopback ports of
this engineer's range (MAVLink 15300-15399, sharing 15400-15499), control requests, truth checks."""

import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
from coopd.daemon import control  # noqa: E402
from coopd.geometry import rotation_angle_deg  # noqa: E402
from firmware_sim.accuracy import map_accuracy  # noqa: E402
from tests.ports import process_slot  # noqa: E402

PYTHON = sys.executable
_BLOCK = 15300 + process_slot(8) * 12


def port_block(i: int) -> tuple[int, int]:
    """(MAVLink base port, sharing base port) for the i-th test of this process (3 ports each)."""
    base = _BLOCK + 3 * (i % 4)
    return base, base + 100


def env() -> dict:
    e = dict(os.environ, PYTHONPATH=str(ROOT), PYTHONUNBUFFERED="1")
    e.pop("NOTIFY_SOCKET", None)
    e.pop("WATCHDOG_USEC", None)
    return e


def wait_until(predicate, timeout: float, poll: float = 0.1):
    """Poll until predicate() is truthy (returned) or timeout (then its last value)."""
    deadline = time.monotonic() + timeout
    while True:
        value = predicate()
        if value or time.monotonic() >= deadline:
            return value
        time.sleep(poll)


SIM_WALL_S = 600
"""How long a Sim runs at most, in wall-clock seconds (pytest's timeout): one left behind by a test
stops by itself, and none stops under a test that is merely slow. --duration counts simulated
seconds, which pass `speed` times faster."""


class Sim:
    """coopd-sim in a subprocess; endpoints parsed from its first JSON line."""

    def __init__(self, workdir: Path, mavlink_port: int, vehicles: int = 1, speed: float = 2.0,
                 world: str = "small_house", seed: int = 0):
        self.world, self.seed = world, seed
        self.camera_dir = workdir / "cam"
        self.camera_dir.mkdir(exist_ok=True)
        self.log = open(workdir / "sim.err", "wb")
        self.proc = subprocess.Popen(
            [PYTHON, "-m", "firmware_sim.cli", "--world", world, "--seed", str(seed), "--speed", str(speed),
             "--route", "builtin", "--vehicles", str(vehicles), "--mavlink-port", str(mavlink_port),
             "--camera-dir", str(self.camera_dir), "--duration", str(SIM_WALL_S * speed), "--gcs-port", "0"],
            stdout=subprocess.PIPE, stderr=self.log, env=env(), cwd=ROOT,
        )
        line = self.proc.stdout.readline()
        if not line:
            raise RuntimeError(f"coopd-sim did not start: {(workdir / 'sim.err').read_text()[-2000:]}")
        self.info = json.loads(line)
        self.vehicles = self.info["vehicles"]

    def camera(self, i: int = 0) -> str:
        assert self.vehicles[i]["camera_unix"] == self.camera_path(self.camera_dir.parent, i)
        return self.vehicles[i]["camera_unix"]

    @staticmethod
    def camera_path(workdir: Path, i: int) -> str:
        """Where coopd-sim --camera-dir workdir/cam serves vehicle i's camera."""
        return str(workdir / "cam" / f"camera{i}.sock")

    def pause(self) -> None:
        self.proc.send_signal(signal.SIGSTOP)

    def resume(self) -> None:
        self.proc.send_signal(signal.SIGCONT)

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGCONT)
            self.proc.terminate()
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5)
        self.proc.stdout.close()
        self.log.close()

    def to_world(self, i: int, origin_fc_enu):
        """Map frame of vehicle i's coopd -> world: its odometry frame is the true start pose
        (origin on the floor, yawed by heading - 90 deg, docs/firmware_sim.md), shifted by the map origin."""
        t = map_to_world(self.vehicles[i]["start_pose"], origin_fc_enu)
        return lambda p: np.asarray(p) @ t[:3, :3].T + t[:3, 3]

    def relative_transform(self, i: int, j: int, origin_i, origin_j) -> np.ndarray:
        """4x4 transform carrying points of vehicle j's map frame into vehicle i's (the true offset)."""
        return true_offset(self.vehicles[i]["start_pose"], origin_i, self.vehicles[j]["start_pose"], origin_j)

    def accuracy(self, grid, i: int, origin_fc_enu) -> dict:
        from firmware_sim.worlds import build_world

        world = build_world(self.world, self.seed)
        gt, gt_origin = world.ground_truth(0.1)
        return map_accuracy(grid, self.to_world(i, origin_fc_enu), gt, gt_origin)


def map_to_world(start_pose, origin_fc_enu) -> np.ndarray:
    """4x4 transform of a coopd's map frame into the simulated world: its odometry frame is the true
    start pose (x, y, z, yaw; origin on the floor, yawed by heading - 90 deg, docs/firmware_sim.md),
    shifted by the map origin (status link.map_origin_fc_enu)."""
    x, y, _, yaw = start_pose
    t = np.eye(4)
    c, s = np.cos(yaw - np.pi / 2), np.sin(yaw - np.pi / 2)
    t[:3, :3] = [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]
    t[:3, 3] = t[:3, :3] @ np.asarray(origin_fc_enu, dtype=np.float64) + [x, y, 0.0]
    return t


def true_offset(start_i, origin_i, start_j, origin_j) -> np.ndarray:
    """4x4 transform carrying points of vehicle j's map frame into vehicle i's (what merging should find)."""
    return np.linalg.inv(map_to_world(start_i, origin_i)) @ map_to_world(start_j, origin_j)


def offset_error(found, truth) -> tuple[float, float]:
    """(metres, degrees) between a found transform (4x4, or 16 numbers row-major) and the true one."""
    found = np.asarray(found, dtype=np.float64).reshape(4, 4)
    return (float(np.linalg.norm(found[:3, 3] - truth[:3, 3])),
            rotation_angle_deg(found[:3, :3].T @ truth[:3, :3]))


def in_process_memory_mb(headroom_mb: int = 512) -> int:
    """memory_mb for a Daemon built inside this test process: the budget counts the process' RSS at
    start as the daemon's baseline, and pytest's RSS grows with every test module it has imported and
    run, so a fixed 512 MiB leaves nothing for grids late in a full run."""
    from coopd.daemon.budget import MIB, read_rss

    return read_rss() // MIB + headroom_mb


def swarm_key_file(workdir: Path) -> Path:
    """The swarm key every daemon of one test shares (made with coopctl's key format once)."""
    from coopd.cli.key_commands import key_file_text

    path = workdir / "swarm.key"
    if not path.exists():
        path.write_text(key_file_text(os.urandom(32)))
        path.chmod(0o600)
    return path


class Coopd:
    """One coopd process (python -m coopd.daemon.main) with its own state dir and control socket."""

    def __init__(self, workdir: Path, name: str, args: list[str], extra_env: dict | None = None):
        self.dir = workdir / name
        self.dir.mkdir(exist_ok=True)
        self.state_dir = self.dir / "state"
        self.socket = str(self.dir / "control.sock")
        self.args = ["--no-config", "--state-dir", str(self.state_dir), "--control-socket", self.socket,
                     "--listen-host", "127.0.0.1", *args]
        if not {"--no-sharing", "--open", "--swarm-key-file"} & set(args):  # secure by default
            self.args += ["--swarm-key-file", str(swarm_key_file(workdir))]
        self.extra_env = extra_env or {}
        self.proc: subprocess.Popen | None = None
        self.logs: list[Path] = []
        self.last_error = ""

    def start(self) -> "Coopd":
        log_path = self.dir / f"coopd-{len(self.logs)}.err"
        self.logs.append(log_path)
        self._log = open(log_path, "wb")
        self.proc = subprocess.Popen([PYTHON, "-m", "coopd.daemon.main", *self.args], stdout=self._log,
                                     stderr=subprocess.STDOUT, env=dict(env(), **self.extra_env), cwd=ROOT)
        return self

    def log_text(self) -> str:
        return "\n".join(p.read_text(errors="replace") for p in self.logs)

    def request(self, cmd: str, args: dict | None = None, **kw):
        return control.request(self.socket, cmd, args, timeout_s=10.0, **kw)

    def status(self) -> dict | None:
        try:
            return self.request("status")[0]
        except control.ControlError as e:
            self.last_error = repr(e)
            return None

    def wait_running(self, timeout: float = 60.0) -> dict:
        s = wait_until(lambda: self._alive_status(), timeout, poll=0.2)
        assert s, f"coopd did not answer within {timeout} s:\n{self.log_text()[-3000:]}"
        return s

    def _alive_status(self):
        rc = self.proc.poll()
        assert rc is None, f"coopd exited with {rc}:\n{self.log_text()[-3000:]}"
        s = self.status()
        return s if s and s.get("state") == "running" else None

    def terminate(self, timeout: float = 10.0) -> tuple[int, float]:
        """SIGTERM; (exit code, seconds it took)."""
        t0 = time.monotonic()
        self.proc.send_signal(signal.SIGTERM)
        rc = self.proc.wait(timeout)
        self._log.close()
        return rc, time.monotonic() - t0

    def kill9(self) -> None:
        self.proc.kill()
        self.proc.wait(10)
        self._log.close()

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(10)
        if self.proc is not None:
            self._log.close()


def workdir(prefix: str) -> Path:
    """A short directory under /tmp (unix socket paths are limited to 107 bytes)."""
    d = Path(tempfile.mkdtemp(prefix=prefix, dir="/tmp"))
    os.chmod(d, 0o755)
    return d


def run_in_threads(daemons) -> list[threading.Thread]:
    """Start in-process daemons and run each one's main loop on a thread of its own."""
    runners = []
    for d in daemons:
        d.start()
        runners.append(threading.Thread(target=d.run, daemon=True))
        runners[-1].start()
    return runners


def stop_all(sim, daemons, runners, wd: Path) -> None:
    """Stop the simulation, then each in-process daemon (its loop thread joined), and remove wd."""
    sim.stop()
    for d, r in zip(daemons, runners, strict=False):
        d.request_stop("test")
        r.join(5)
        d.shutdown()
    shutil.rmtree(wd, ignore_errors=True)


class NotifyListener:
    """A NOTIFY_SOCKET of our own, read continuously as systemd does: (monotonic time, message) of
    every datagram."""

    def __init__(self, directory: Path):
        self.path = str(directory / "notify.sock")
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.bind(self.path)
        self.sock.settimeout(0.1)
        self.messages: list[tuple[float, str]] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._read, daemon=True)
        self._thread.start()

    def _read(self) -> None:
        while not self._stop.is_set():
            try:
                self.messages.append((time.monotonic(), self.sock.recv(4096).decode()))
            except TimeoutError:
                continue
            except OSError:
                return

    def drain(self, seconds: float = 0.0) -> list[tuple[float, str]]:
        time.sleep(seconds)
        return list(self.messages)

    def with_field(self, prefix: str) -> list[tuple[float, str]]:
        return [(t, m) for t, m in list(self.messages) if any(f.startswith(prefix) for f in m.split("\n"))]

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2)
        self.sock.close()

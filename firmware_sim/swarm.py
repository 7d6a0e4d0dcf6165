"""A simulated swarm: firmware_sim flying N drones in-process, and one real `coopd` process per
drone, each on its own address (a network namespace per drone when root and iproute2 are there,
else loopback addresses). Used by scripts/demo, the swarm benchmark and the swarm fault tests.

    with Swarm(SwarmSettings(world="small_house", drones=3)) as swarm:
        swarm.start(); swarm.fly(); swarm.wait_landed(); swarm.merge_until_converged()

Drone i (0-based) is vehicle id i+1 and host i+1 on the swarm network; its MAVLink arrives from
the simulator on <mavlink_address(i)>:<mavlink_base+i> (in netns mode over the drone's own wired
FC cable, not the radio, so either can be cut alone), its camera on a unix socket in the work directory,
its map server listens on <host>:<sharing_port>, and peers are found by scanning the swarm's
address range. stop() (also on Ctrl-C, and idempotent) kills every process and removes every
namespace and file it made.
"""

from __future__ import annotations

import ipaddress
import math
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from coopd.cli.key_commands import key_file_text
from coopd.daemon import control
from coopd.daemon.merger import in_global_map
from coopd.geometry import invert
from firmware_sim import accuracy as acc
from firmware_sim.netns import LoopbackLab, NetnsLab, netns_unavailable_reason, remove_stale
from firmware_sim.simulation import Simulation
from firmware_sim.worlds import build_world

ROOT = Path(__file__).resolve().parents[1]
NETNS_TAG = "coopd-swarm"


@dataclass(frozen=True)
class SwarmSettings:
    """What to fly and how the daemons are set up."""

    world: str = "small_house"
    drones: int = 3
    seed: int = 1
    speed: float = 2.0
    """Simulated seconds per wall second."""
    network: str = "auto"
    """'netns', 'loopback', or 'auto' (netns when available)."""
    subnet: str = "10.214.1"
    """Swarm network in netns mode (addresses exist only inside the namespaces)."""
    fc_subnet: str = "10.215.1"
    """The /24 the drones' FC cables take their /30s from in netns mode (root side .4i+1)."""
    mavlink_base: int = 14740
    sharing_port: int = 17400
    memory_mb: int = 768
    merge_period_s: float = 5.0
    checkpoint_period_s: float = 30.0
    swarm_key: bytes | None = None
    """Shared swarm key (written to a key file for every daemon); None: a random one per swarm,
    unless `open`."""
    open: bool = False
    """No swarm key: the daemons run with sharing.open = true (thesis-format interop)."""
    drone_keys: dict = field(default_factory=dict)
    """Per-drone key overrides {drone index: key bytes}, e.g. one drone with the wrong swarm key."""
    config: dict = field(default_factory=dict)
    """Extra coopd.toml settings: {section: {key: value}}, e.g. {"merging": {"distributed": False}}."""
    viewer_port: int = 0
    """> 0: every daemon serves the live view (Foxglove WebSocket) on its swarm address at this port;
    an address other than loopback (netns mode) with viewer.open, as the protocol has no authentication."""
    noise: str = "default"
    autopilot: str = "px4"
    """The flight controllers' MAVLink personality: 'px4' or 'ardupilot' (ArduCopter)."""


def toml_value(v) -> str:
    """A Python value as a TOML literal (the few types a coopd.toml uses)."""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int | float):
        return repr(v)
    if isinstance(v, str | Path):
        return '"' + str(v).replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, list | tuple):
        return "[" + ", ".join(toml_value(x) for x in v) + "]"
    raise TypeError(f"no TOML literal for {type(v).__name__}")


def render_config(sections: dict) -> str:
    """{section: {key: value}} as coopd.toml text; a dict value is a sub-table ([section.key])."""
    out = []
    for name, table in sections.items():
        out.append(f"[{name}]")
        out.extend(f"{k} = {toml_value(v)}" for k, v in table.items() if not isinstance(v, dict))
        out.append("")
        subtables = {f"{name}.{k}": v for k, v in table.items() if isinstance(v, dict)}
        if subtables:
            out.append(render_config(subtables))
    return "\n".join(out)


class Daemon:
    """One coopd process of the swarm: its files, its process, its control socket."""

    def __init__(self, index: int, workdir: Path):
        self.index = index
        self.vehicle_id = index + 1
        self.dir = workdir / f"d{self.vehicle_id}"
        self.dir.mkdir(parents=True, exist_ok=True)
        self.config_path = self.dir / "coopd.toml"
        self.state_dir = self.dir / "state"
        self.socket = self.dir / "control.sock"
        self.log_path = self.dir / "coopd.log"
        self.proc: subprocess.Popen | None = None
        self.starts = 0
        self.killed = False
        """Stopped on purpose by kill_daemon (until restarted): check_alive does not complain."""

    def running(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def request(self, cmd: str, args: dict | None = None, timeout_s: float = 5.0, **kw):
        return control.request(self.socket, cmd, args, timeout_s=timeout_s, **kw)

    def status(self, timeout_s: float = 5.0) -> dict | None:
        """The daemon's status, or None while it does not answer."""
        try:
            return self.request("status", timeout_s=timeout_s)[0]
        except (control.ControlError, OSError):
            return None

    def log_tail(self, chars: int = 3000) -> str:
        try:
            return self.log_path.read_text(errors="replace")[-chars:]
        except OSError:
            return ""


class Swarm:
    """Owns the simulation, the swarm network and the daemons; stop() tears everything down."""

    def __init__(self, settings: SwarmSettings, workdir: Path | None = None,
                 say: Callable[[str], None] = print):
        if not 1 <= settings.drones <= 32:
            raise ValueError("drones must be within 1..32")
        self.settings = settings
        self._random_key = os.urandom(32)
        """The swarm's key when settings.swarm_key is None (and not open): secure by default."""
        self.say = say
        self.own_workdir = workdir is None
        # Short paths: unix socket paths are limited to 107 bytes.
        self.workdir = workdir or Path(tempfile.mkdtemp(prefix="coopd-swarm-", dir="/tmp"))
        os.chmod(self.workdir, 0o755)
        self.daemons = [Daemon(i, self.workdir) for i in range(settings.drones)]
        self.sim: Simulation | None = None
        self.lab: NetnsLab | LoopbackLab | None = None
        self.world = build_world(settings.world, settings.seed)
        self.hostiles: list[subprocess.Popen] = []
        self.mounts: list[Path] = []
        self._stopped = False

    # ------------------------------------------------------------------------------ set-up
    @property
    def network_mode(self) -> str:
        return "none" if self.lab is None else self.lab.mode

    def _make_lab(self):
        s = self.settings
        reason = netns_unavailable_reason()
        if s.network == "netns" and reason:
            raise RuntimeError(f"network namespaces unavailable: {reason}")
        if s.network == "netns" or (s.network == "auto" and reason is None):
            stale = remove_stale(NETNS_TAG)
            if stale:
                self.say(f"swarm: removed {len(stale)} namespaces left by a killed run")
            return NetnsLab(NETNS_TAG, s.subnet, s.fc_subnet)
        return LoopbackLab(NETNS_TAG)

    def address(self, i: int) -> str:
        """Drone i's address on the swarm network."""
        return self.lab.address(i + 1)

    def viewer_url(self, i: int) -> str | None:
        """Where the Foxglove app reaches drone i's live view (settings.viewer_port), or None."""
        return f"ws://{self.address(i)}:{self.settings.viewer_port}" if self.settings.viewer_port else None

    def mavlink_address(self, i: int) -> str:
        """Where drone i's coopd receives MAVLink: its end of the FC cable (netns), else its address."""
        if self.network_mode == "netns":
            return self.lab.fc_addresses(i + 1)[1]
        return self.address(i)

    def key_file(self, i: int) -> Path | None:
        """Drone i's swarm key file (its override, else the shared key), or None without a key."""
        if i in self.settings.drone_keys:
            return self.workdir / f"swarm-d{i + 1}.key"
        return None if self.settings.open else self.workdir / "swarm.key"

    def start(self, wait: bool = True) -> None:
        """Network, simulation (drones idle on the ground), then the daemons: the first alone, so
        it fills numba's kernel cache that the others then load."""
        s = self.settings
        self.lab = self._make_lab()
        for i in range(s.drones):
            self.lab.add_host(i + 1)
        sim_host = self.lab.attach_root()
        if self.network_mode == "netns":
            sim_host = [self.lab.add_fc_link(i + 1)[0] for i in range(s.drones)]
        for i in range(s.drones):
            key_file = self.key_file(i)
            if key_file is not None and not key_file.exists():
                key = s.drone_keys.get(i, s.swarm_key) or self._random_key
                key_file.write_text(key_file_text(key))
                key_file.chmod(0o600)
        self.sim = Simulation(self.world, s.drones, seed=s.seed, speed=s.speed, noise=s.noise,
                              mavlink_base_port=s.mavlink_base,
                              mavlink_hosts=[self.mavlink_address(i) for i in range(s.drones)],
                              mavlink_bind_host=sim_host, camera_dir=str(self.workdir),
                              autopilot=s.autopilot)
        self.sim.start()
        self.start_daemon(0)
        if wait:
            self.wait_mapping([0], "compiling kernels (once; later starts load them from the cache)")
        for i in range(1, s.drones):
            self.start_daemon(i)
        if wait:
            self.wait_mapping(range(s.drones), "starting the other daemons")

    def config_sections(self, i: int) -> dict:
        """Drone i's coopd.toml as {section: {key: value}} (settings.config merged over it)."""
        s = self.settings
        d = self.daemons[i]
        sections = {
            "vehicle": {"id": d.vehicle_id,
                        "mavlink": f"udpin:{self.mavlink_address(i)}:{s.mavlink_base + i}"},
            "camera": {"source": f"socket:{self.workdir / f'camera{i}.sock'}"},
            "sharing": {"listen_host": self.address(i), "port": s.sharing_port,
                        "peers": [self.lab.range_spec(s.drones)], "peer_ports": [s.sharing_port],
                        "scan_period_s": 1.0},
            "merging": {"period_s": s.merge_period_s},
            "daemon": {"memory_mb": s.memory_mb, "state_dir": str(d.state_dir),
                       "control_socket": str(d.socket), "checkpoint_period_s": s.checkpoint_period_s},
        }
        if s.viewer_port:
            sections["viewer"] = {"enabled": True, "host": self.address(i), "port": s.viewer_port,
                                  "open": not ipaddress.ip_address(self.address(i)).is_loopback}
        if self.key_file(i) is not None:
            sections["sharing"]["swarm_key_file"] = str(self.key_file(i))
        else:
            sections["sharing"]["open"] = True
        for name, table in s.config.items():
            sections.setdefault(name, {}).update(table)
        return sections

    def start_daemon(self, i: int) -> Daemon:
        """Start (or restart) drone i's coopd in its namespace; its log is appended to."""
        d = self.daemons[i]
        if d.running():
            raise RuntimeError(f"coopd of drone {d.vehicle_id} is already running")
        d.config_path.write_text(render_config(self.config_sections(i)))
        env = dict(os.environ, PYTHONPATH=str(ROOT), PYTHONUNBUFFERED="1")
        env.pop("NOTIFY_SOCKET", None)
        env.pop("WATCHDOG_USEC", None)
        argv = [sys.executable, "-m", "coopd.daemon.main", "--config", str(d.config_path)]
        with open(d.log_path, "ab") as log:
            d.proc = subprocess.Popen(self.lab.command(i + 1, argv), stdout=log, stderr=subprocess.STDOUT,
                                      env=env, cwd=ROOT)
        d.starts += 1
        d.killed = False
        return d

    def kill_daemon(self, i: int, sig: int = signal.SIGKILL, timeout_s: float = 10.0) -> int:
        """Send sig to drone i's coopd and wait for it to exit; returns its exit code."""
        d = self.daemons[i]
        if not d.running():
            return d.proc.returncode if d.proc is not None else 0
        d.killed = True
        d.proc.send_signal(sig)
        try:
            return d.proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            d.proc.kill()
            return d.proc.wait(10)

    # ------------------------------------------------------------------------------ faults
    def radio(self, i: int, up: bool) -> None:
        """Cut or restore drone i's radio (its port on the swarm bridge); its FC link stays. netns only."""
        self.lab.link(i + 1, up)

    def fc_link(self, i: int, up: bool) -> None:
        """Cut or restore drone i's wired flight-controller link; its radio stays. netns only."""
        self.lab.fc_link(i + 1, up)

    def small_disk(self, i: int, size: str = "16m") -> Path:
        """Put drone i's state directory on its own tmpfs of `size` (before start_daemon), so that
        fill_disk() fills only that drone's disk; unmounted by stop(). Needs root."""
        d = self.daemons[i]
        d.state_dir.mkdir(parents=True, exist_ok=True)
        subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size},mode=0755", "tmpfs", str(d.state_dir)],
                       check=True, capture_output=True, timeout=10)
        self.mounts.append(d.state_dir)
        return d.state_dir

    def fill_disk(self, i: int, chunk: int = 1 << 16) -> int:
        """Fill drone i's state directory's file system to the last byte (a filler file, removed by
        free_disk); returns the bytes written. Meant for a small_disk()."""
        written = 0
        buf = b"\0" * chunk
        with open(self.daemons[i].state_dir / "filler", "ab", buffering=0) as f:
            while chunk:
                try:
                    written += f.write(buf[:chunk])
                except OSError:
                    chunk //= 2  # the last bytes: smaller writes until not even one byte fits
        return written

    def free_disk(self, i: int) -> None:
        """Remove fill_disk()'s filler file."""
        (self.daemons[i].state_dir / "filler").unlink(missing_ok=True)

    def start_hostile(self, seconds: float, host: int = 200, max_connections: int = 1000) -> subprocess.Popen:
        """A hostile host (its own namespace on the swarm bridge, netns only) attacking every daemon's
        map server for `seconds` (firmware_sim.attacker); its JSON summary is on the Popen's stdout."""
        if self.network_mode != "netns":
            raise RuntimeError("a hostile host needs network namespaces (root and iproute2)")
        if host in self.lab.hosts or host <= self.settings.drones:
            raise ValueError(f"host {host} is taken")
        self.lab.add_host(host)
        argv = [sys.executable, "-m", "firmware_sim.attacker", "--seconds", str(seconds),
                "--max-connections", str(max_connections),
                "--block-size", str(self.settings.config.get("sharing", {}).get("block_size", 4096))]
        for i in range(self.settings.drones):
            argv += ["--target", f"{self.address(i)}:{self.settings.sharing_port}"]
        env = dict(os.environ, PYTHONPATH=str(ROOT))
        proc = subprocess.Popen(self.lab.command(host, argv), stdout=subprocess.PIPE,
                                stderr=subprocess.STDOUT, text=True, env=env, cwd=ROOT)
        self.hostiles.append(proc)
        return proc

    # ------------------------------------------------------------------------------ watching
    def check_alive(self) -> None:
        for d in self.daemons:
            if d.proc is not None and not d.killed and d.proc.poll() is not None:
                raise RuntimeError(f"coopd of drone {d.vehicle_id} exited with code {d.proc.returncode}; "
                                   f"log {d.log_path}:\n{d.log_tail(1500)}")

    def status(self, i: int) -> dict | None:
        return self.daemons[i].status()

    def statuses(self) -> list[dict | None]:
        return [d.status() for d in self.daemons]

    def wait_for(self, predicate: Callable[[], bool], limit_s: float, what: str,
                 poll_s: float = 1.0) -> float:
        """Poll predicate (daemons checked alive) until true; seconds taken, or RuntimeError."""
        t0 = time.monotonic()
        while time.monotonic() - t0 < limit_s:
            self.check_alive()
            if predicate():
                return time.monotonic() - t0
            time.sleep(poll_s)
        raise RuntimeError(f"{what}: not reached after {limit_s:.0f} s; logs in {self.workdir}")

    def wait_mapping(self, drones, what: str, limit_s: float = 240.0) -> float:
        """Until every daemon in `drones` answers and maps (link up, frames arriving)."""
        drones = list(drones)
        self.say(f"swarm: {what} ...")

        def mapping():
            statuses = [self.status(i) for i in drones]
            return all(s and (s.get("mapping") or {}).get("state") == "mapping" for s in statuses)

        took = self.wait_for(mapping, limit_s, "daemons mapping")
        self.say(f"swarm: {len(drones)} daemon(s) mapping after {took:.0f} s")
        return took

    # ------------------------------------------------------------------------------ flying
    def fly(self) -> None:
        """Every drone takes off and flies its built-in exploration route."""
        self.sim.fly_builtin_routes()

    def landed(self) -> bool:
        return all(self.sim.route_finished(i) for i in range(self.settings.drones))

    def merged_vehicles(self, s: dict | None) -> dict[int, dict]:
        """Vehicle id -> offset entry of every map merged into a daemon's global map (provisional
        merges, held out of it, do not count)."""
        offsets = ((s or {}).get("merges") or {}).get("offsets") or {}
        return {int(k): v for k, v in offsets.items() if in_global_map(v)}

    def converged(self) -> bool:
        """Every daemon has merged every other drone's map."""
        n = self.settings.drones
        return all(len(self.merged_vehicles(self.status(i))) >= n - 1 for i in range(n))

    def merge_now(self, i: int, timeout_s: float = 120.0) -> dict | None:
        try:
            return self.daemons[i].request("merge-now", timeout_s=timeout_s)[0]
        except (control.ControlError, OSError) as e:
            self.say(f"swarm: merge-now on drone {i + 1}: {e}")
            return None

    def merge_everywhere(self, timeout_s: float = 120.0) -> list[dict | None]:
        """`coopctl merge-now` on every daemon at once (they merge in parallel); their outcomes."""
        with ThreadPoolExecutor(max_workers=len(self.daemons)) as pool:
            return list(pool.map(lambda i: self.merge_now(i, timeout_s), range(len(self.daemons))))

    def merge_until_converged(self, limit_s: float = 90.0,
                              progress: Callable[[], None] | None = None) -> bool:
        """Merge on every daemon until each has merged every other map or limit_s passed.

        Two merges run everywhere first, as the daemons' own periodic merges would within two
        periods: one on the maps as they are now, one more that sees them settled (merger.py
        searches a map once more on the final maps when its transform was decided on smaller ones)."""
        deadline = time.monotonic() + limit_s
        for _ in range(2):
            self.check_alive()
            self.merge_everywhere(timeout_s=max(5.0, deadline - time.monotonic()))
        while True:
            self.check_alive()
            if self.converged():
                return True
            left = deadline - time.monotonic()
            if left <= 0:
                return False
            self.merge_everywhere(timeout_s=max(5.0, left))
            if progress is not None:
                progress()

    # ------------------------------------------------------------------------------ truth
    def map_to_world(self, i: int, status: dict | None) -> np.ndarray:
        """Truth: drone i's map frame in the world: its FC's reporting frame as drifted when its
        daemon took the map origin (status link.map_origin_fc_enu / map_origin_t_fc), moved there."""
        link = (status or {}).get("link") or {}
        return acc.map_frame_in_world(self.sim.vehicle(i).odometry, link.get("map_origin_fc_enu"),
                                      link.get("map_origin_t_fc"))

    def offset_errors(self, i: int, statuses: list[dict | None]) -> dict[int, dict]:
        """Per drone merged into drone i's global map: estimated offset and its error vs truth."""
        out = {}
        truth_i = self.map_to_world(i, statuses[i])
        for vid, entry in self.merged_vehicles(statuses[i]).items():
            j = vid - 1
            if not 0 <= j < self.settings.drones or j == i:
                continue
            est = np.array(entry["transform"], float).reshape(4, 4)
            error_m, error_deg = acc.offset_error(est, invert(truth_i) @ self.map_to_world(j, statuses[j]))
            out[vid] = {
                "translation_m": [float(v) for v in est[:3, 3]],
                "yaw_deg": math.degrees(math.atan2(est[1, 0], est[0, 0])),
                "error_m": error_m,
                "error_deg": error_deg,
            }
        return out

    def tracks_in_map(self, i: int, statuses: list[dict | None]) -> tuple[dict[int, np.ndarray], list[int]]:
        """Every drone's true track in drone i's map frame, for its global map's top view: its own
        through where its map frame truly is, another's through drone i's merge estimate of that
        drone's map (a merge error shows as a track off the walls); drones not merged into drone i's
        global map are in the second list (see accuracy.tracks_in_frame)."""
        to_map_i = invert(self.map_to_world(i, statuses[i]))
        merged = self.merged_vehicles(statuses[i])
        frames: dict[int, np.ndarray | None] = {i + 1: to_map_i}
        for j in range(self.settings.drones):
            entry = merged.get(j + 1)
            if j != i:
                frames[j + 1] = None if entry is None or not statuses[j] else (
                    np.array(entry["transform"], float).reshape(4, 4)
                    @ invert(self.map_to_world(j, statuses[j])))
        trajectories = {j + 1: self.sim.trajectory(j) for j in range(self.settings.drones)}
        return acc.tracks_in_frame(trajectories, frames)

    def map_accuracy(self, i: int, grid, status: dict | None) -> dict:
        """Occupied-cell precision/recall of a map of drone i (its frame) vs the world's ground truth
        in the region it explored, and the odometry drift the emulator put in since its map origin."""
        gt, gt_origin = self.world.ground_truth(0.1)
        out = acc.map_accuracy(grid, acc.transform_points(self.map_to_world(i, status)), gt, gt_origin)
        t0 = (((status or {}).get("link") or {}).get("map_origin_t_fc"))
        if t0 is not None:
            odometry = self.sim.vehicle(i).odometry
            out["drift_m"], out["drift_deg"] = acc.drift_since(odometry, t0, self.sim.time)
        return {k: round(v, 4) if isinstance(v, float) else v for k, v in out.items()}

    # ------------------------------------------------------------------------------ tear-down
    def stop(self, keep_files: bool = False) -> None:
        """SIGTERM every daemon (SIGKILL after 10 s), stop the simulation, remove the network and,
        unless keep_files, the work directory. Idempotent."""
        if self._stopped:
            return
        self._stopped = True
        for proc in self.hostiles:
            if proc.poll() is None:
                proc.kill()
            proc.wait(10)
        for d in self.daemons:
            if d.running():
                d.proc.send_signal(signal.SIGTERM)
        deadline = time.monotonic() + 10
        for d in self.daemons:
            if d.proc is None:
                continue
            try:
                d.proc.wait(timeout=max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                d.proc.kill()
                d.proc.wait()
        if self.sim is not None:
            self.sim.stop()
        for mount in self.mounts:
            subprocess.run(["umount", "-l", str(mount)], capture_output=True, timeout=10)
        self.mounts.clear()
        if self.lab is not None:
            self.lab.cleanup()
        if self.own_workdir and not keep_files:
            shutil.rmtree(self.workdir, ignore_errors=True)

    def __enter__(self) -> Swarm:
        return self

    def __exit__(self, *exc) -> None:
        self.stop()

"""The Daemon: owns every stage of one vehicle's coopd and the threads that run them.

    daemon = Daemon(load_config(path)); daemon.start(); daemon.run(); daemon.shutdown()

| thread          | role (nice) | loop                                                         |
|-----------------|-------------|--------------------------------------------------------------|
| coopd-mavlink   | mavlink -5  | VehicleLink.run: FC link -> pose buffer                      |
| coopd-camera    | camera -3   | depth source -> LatestSlot (newest wins, drops counted)      |
| coopd-mapping   | mapping -3  | newest frame + interpolated pose -> local grid               |
| coopd-sharing   | sharing 0   | starts the sharing service (its threads inherit), publishes |
| coopd-merging   | merging +10 | Merger.run: local + received -> global map                   |
| coopd-obstacles | obstacles -3| ObstacleReporter.run: map near the vehicle -> FC ([obstacles]) |
| coopd-viewer    | viewer +15  | MapViewer.run: map, poses, status -> Foxglove app ([viewer]) |
| coopd-control   | control 0   | ControlServer: coopctl                                       |
| main            | -           | run(): checkpoints, memory ledger, sd_notify STATUS, health  |
| coopd-watchdog  | -           | WATCHDOG=1 while main, mapping, merging, sharing, obstacles progress |
"""

import json
import logging
import os
import signal
import threading
import time
from collections import deque
from dataclasses import replace
from pathlib import Path

import numpy as np

from coopd.camera import (
    CameraUnavailable,
    LatestSlot,
    RealSenseSource,
    SocketDepthSource,
    SocketSourceConfig,
    load_pyrealsense2,
)
from coopd.daemon.budget import MemoryBudget
from coopd.daemon.checkpoint import VERSION_FILE, CheckpointStore, VersionReserve
from coopd.daemon.config import Config
from coopd.daemon.control import DEFAULT_MAX_REPLY_BUFFER, BlobReply, CommandFailed, ControlServer
from coopd.daemon.gcs import GcsReporter, Health
from coopd.daemon.merge_state import MergerSettings, MergeSources
from coopd.daemon.merger import Merger, find_merge_all, in_global_map, mergeable_cells
from coopd.daemon.notify import Notifier, WatchdogPinger
from coopd.daemon.obstacles import ObstacleReporter
from coopd.daemon.threads import ThreadPriorities, WorkerProgress
from coopd.daemon.warmup import warm_up_kernels
from coopd.geometry import euler_to_matrix, matrix_to_quat
from coopd.grid import OccupancyGrid
from coopd.io.atomic import PRIVATE, write_atomic
from coopd.mapping import CameraMount, FrameRejected, Mapper
from coopd.mapping.association import FrameAssociator
from coopd.mapping.reanchor import FrameReanchor
from coopd.sharing import swarmkey
from coopd.sharing import versions as map_versions
from coopd.sharing.mtp import ACK_VERSION
from coopd.sharing.peers import MessageSummary
from coopd.sharing.service import SharingConfig as ServiceSharingConfig
from coopd.sharing.service import SharingService, wire_verifier
from coopd.sharing.transport import TransportSettings
from coopd.sharing.wire import (
    MapMeta,
    MergeResultMessage,
    encode_map,
    encode_merge_result,
    with_version,
)
from coopd.vehicle import LinkConfig, VehicleLink
from coopd.vehicle.signing import read_signing_key

from . import status as status_report

log = logging.getLogger("coopd.daemon")

FRAME_FILE = "map-frame.json"
"""The map frame's origin in the FC's local frame, kept next to the checkpoints so a restarted
daemon continues the same map frame (the first odometry sample after a restart is elsewhere)."""
MAIN_PERIOD_S = 0.2
STATUS_PERIOD_S = 5.0
MEMORY_PERIOD_S = 1.0
"""The memory ledger and RSS are checked this often (reading RSS is a /proc read)."""
LOG_PERIOD_S = 60.0
PUBLISH_PERIOD_S = 1.0
NEW_EPOCH_MIN_S = 5.0
"""A peer refusing our map's version starts a new version epoch at most this often."""
HEALTH_MAX_AGE_S = 3.0
"""Every watched thread (main, mapping, merging, sharing, obstacles) must have looped within this time for
WATCHDOG=1, or be inside a long step (a merge, a publish) that used CPU within HEALTH_BUSY_QUIET_S."""
HEALTH_BUSY_QUIET_S = 30.0
LATENCY_WINDOW = 2000
SNAPSHOT_PAD_CELLS = 4
"""Unknown cells kept around the known box of a snapshot (room for the merge's filters)."""
MERGE_NOW_TIMEOUT_S = 100.0
SHUTDOWN_JOIN_S = 2.0
FROM_BUILD = "from-build"
"""Daemon(merge_fn=FROM_BUILD): coopd.merging.merge_all if this build has it (None: not available)."""


class RssWatch:
    """Logs the process RSS crossing the memory budget: one WARNING when it goes over (with the
    numbers and the ledger), one INFO when it is back under UNDER_FRACTION of the budget (so RSS
    hovering at the budget is not a line per check); the state and the crossings for status."""

    UNDER_FRACTION = 0.95

    def __init__(self, budget: MemoryBudget):
        self.budget = budget
        self.crossings = 0
        self.over_since: float | None = None
        self.peak_over = 0

    def check(self, rss: int) -> None:
        """Called with a fresh RSS reading (main loop)."""
        limit = self.budget.budget_bytes
        if self.over_since is None and rss > limit:
            self.over_since, self.crossings, self.peak_over = time.monotonic(), self.crossings + 1, rss
            snap = self.budget.snapshot()
            ledger = ", ".join(f"{k} {v / 2**20:.1f}" for k, v in snap["entries"].items()) or "nothing"
            log.warning(
                "memory: RSS %.0f MiB is over the budget of %.0f MiB (memory_mb) by %.0f MiB; baseline "
                "%.0f MiB, grids reserved %.1f MiB (%s); crossing %d",
                rss / 2**20, limit / 2**20, (rss - limit) / 2**20, snap["baseline_bytes"] / 2**20,
                snap["reserved_bytes"] / 2**20, ledger, self.crossings,
            )
        elif self.over_since is not None:
            self.peak_over = max(self.peak_over, rss)
            if rss <= self.UNDER_FRACTION * limit:
                log.info(
                    "memory: RSS %.0f MiB back under the budget of %.0f MiB after %.1f s over "
                    "(peak %.0f MiB)",
                    rss / 2**20, limit / 2**20, time.monotonic() - self.over_since, self.peak_over / 2**20,
                )
                self.over_since = None

    def status(self) -> dict:
        since = self.over_since
        return {
            "over_budget": since is not None,
            "over_budget_for_s": None if since is None else round(time.monotonic() - since, 1),
            "over_budget_crossings": self.crossings,
        }


class StartupError(RuntimeError):
    """The daemon cannot start (socket in use, camera module missing, ...); the message says why."""


# ------------------------------------------------------------------------------ config adapters
def link_config(config: Config) -> LinkConfig:
    v = config.vehicle
    key = None
    if v.signing_key_file:
        try:
            key = read_signing_key(v.signing_key_file)
        except (OSError, ValueError) as e:
            raise StartupError(f"vehicle.signing_key_file: {e}") from e
    return LinkConfig(
        signing_key=key,
        connection=v.mavlink,
        source_system=v.id,
        target_system=v.id,
        odometry_rate_hz=v.odometry_rate_hz,
        link_timeout_s=max(v.link_timeout_s, v.odometry_timeout_s),
        odometry_timeout_s=v.odometry_timeout_s,
        watch_obstacle_demand=obstacles_on(config),
    )


def obstacles_on(config: Config) -> bool:
    """The obstacles thread runs: it sends always, or while the FC asks for obstacle data."""
    return config.obstacles.enabled or config.obstacles.when_fc_asks


def camera_mount(config: Config) -> CameraMount:
    roll, pitch, yaw = np.radians(config.vehicle.camera_mount_rpy_deg)
    return CameraMount(
        np.array(config.vehicle.camera_mount_m, dtype=np.float64),
        matrix_to_quat(euler_to_matrix(roll, pitch, yaw)),
    )


def local_grid_cap(config: Config, budget: MemoryBudget) -> int:
    """Cells the local grid may grow to: a quarter of the grid budget (the local map, its snapshot
    for sharing/checkpoints, the global map and merge scratch must all fit), within the config's cap."""
    return min(config.mapping.growth.max_cells, max(budget.grid_budget // 4, 1))


def control_reply_buffer(budget: MemoryBudget) -> int:
    """Bytes of control replies that may wait for slow readers: 1/8 of the room for grids, within
    1..64 MiB (one reply alone may exceed it: a map the daemon holds anyway)."""
    return min(DEFAULT_MAX_REPLY_BUFFER, max(1 << 20, budget.grid_budget // 8))


def swarm_key(s) -> bytes | None:
    """The swarm key of the [sharing] table, read as `coopctl key check` reads it; StartupError if
    there is none and the server was not opened explicitly (secure by default)."""
    if s.swarm_key_file and s.open:
        raise StartupError("sharing: swarm_key_file is set and open = true; choose one")
    if not s.swarm_key_file:
        if not s.open:
            raise StartupError("sharing: no swarm key. Run `coopctl key generate --out "
                               "/etc/coopd/swarm.key`, copy the file to every vehicle of the swarm and set "
                               "sharing.swarm_key_file; or set sharing.open = true to accept maps from any "
                               "host")
        log.warning("sharing is OPEN (sharing.open = true, no swarm key): any host on the network can send "
                    "maps under any vehicle id and read ours; set sharing.swarm_key_file to close it")
        return None
    try:
        key = swarmkey.read_key_file(s.swarm_key_file)
    except (OSError, ValueError) as e:
        raise StartupError(f"sharing.swarm_key_file: {e}") from e
    if key is None:
        raise StartupError(f"sharing.swarm_key_file: {s.swarm_key_file} is empty")
    return key


def sharing_config(config: Config, budget: MemoryBudget) -> ServiceSharingConfig:
    s = config.sharing
    key = swarm_key(s)
    if not map_versions.clock_is_set():
        log.warning("system clock reads %s, before it can have been set (no NTP or GPS time yet): peers' "
                    "map versions are checked for order only, not against the clock, until it is",
                    time.strftime("%Y-%m-%d %H:%M:%S", time.gmtime()))
    transport = TransportSettings(
        block_size=s.block_size,
        max_bytes=s.max_map_bytes,
        max_cells=s.max_map_cells,
        swarm_key=key,
    )
    return ServiceSharingConfig(
        vehicle_id=config.vehicle.id,
        listen_host=s.listen_host,
        port=s.port,
        peers=s.peers,
        peer_ports=s.peer_ports,
        scan_period=s.scan_period_s,
        grace_period=s.grace_period_s,
        relay=s.relay,
        deltas=s.deltas,
        max_received_bytes=max(budget.grid_budget // 4, 1),
        allowed_vehicles=frozenset(s.allowed_vehicles),
        max_epoch_ahead_s=s.max_clock_skew_s,
        transport=transport,
        mtp=s.transport in ("mtp", "both"),
        zenoh=s.zenoh if s.transport in ("zenoh", "both") else None,
    )


def save_map_frame(state_dir, vehicle_id: int, origin_fc_enu) -> None:
    """Write FRAME_FILE atomically: where the local map's frame sits in the FC's local frame, read
    back on start with the local checkpoint (tools that prepare a state dir write it the same way)."""
    data = json.dumps({"vehicle_id": vehicle_id, "origin_fc_enu": [float(v) for v in origin_fc_enu]})
    write_atomic(Path(state_dir) / FRAME_FILE, data.encode(), PRIVATE)


# ------------------------------------------------------------------------------------ the daemon
class Daemon:
    """One vehicle's coopd: the stages, their threads, persistence, control and health."""

    def __init__(self, config: Config, notifier: Notifier | None = None, merge_fn=FROM_BUILD):
        self.config = config
        self.vehicle_id = config.vehicle.id
        self.pid = os.getpid()
        self.started = time.monotonic()
        self.state = "starting"
        # The socket backend, not libsystemd's sd_notify: that one blocks on a full notify queue while
        # holding the GIL, which froze every thread of the daemon, mapping included (notify.py).
        self.notifier = notifier if notifier is not None else Notifier("socket")
        found = find_merge_all() if merge_fn is FROM_BUILD else (merge_fn, None)
        self.merge_fn, self.merge_start_error = found
        self.notifier.extend_timeout(120)
        self._warm_up()  # first: the kernels' memory then belongs to the budget's baseline
        self.budget = MemoryBudget.from_mb(config.daemon.memory_mb)
        self.rss_watch = RssWatch(self.budget)
        self.priorities = ThreadPriorities()
        self.state_dir = Path(config.daemon.state_dir)
        self.store = CheckpointStore(self.state_dir, keep=config.daemon.checkpoint_keep)
        self.versions = VersionReserve(self.state_dir)
        self.epoch = self.versions.new_epoch()
        """The version epoch of the maps we publish (docs/protocol.md, "Map versions")."""
        self._epoch_at = time.monotonic()
        self._own_refusal: tuple[int, int, int] | None = None
        self.link = VehicleLink(link_config(config))
        self.gcs = GcsReporter(self.link)
        self.slot: LatestSlot = LatestSlot()
        self.camera = self._make_camera()
        self.associator = FrameAssociator(self.link, camera_mount(config), config.camera.pose_wait_s)
        self.mapper = self._make_mapper()
        self.reanchor = FrameReanchor(self.link.frames, self.mapper, camera_mount(config),
                                      pose_wait_s=config.camera.pose_wait_s)
        self.latency_s: deque[float] = deque(maxlen=LATENCY_WINDOW)
        watched = (["main", "mapping", "merging"] + (["sharing"] if config.sharing.enabled else [])
                   + (["obstacles"] if obstacles_on(config) else []))  # the FC's obstacle feed
        self.progress = WorkerProgress(watched, HEALTH_MAX_AGE_S, HEALTH_BUSY_QUIET_S)
        self._stalled: dict[str, str] = {}
        self._health_lock = threading.Lock()
        self.frames_mapped = 0
        self.mapping_errors = 0
        self.sharing = (
            SharingService(
                sharing_config(config, self.budget),
                verify=wire_verifier(config.sharing.max_map_cells, config.sharing.max_map_bytes),
                on_map=self._on_map_received,
                on_result=lambda _vid, _version: self.merger.on_peer_result(),
                budget=self.budget,
                cell_cap=self.mergeable_cells,
                on_own_refused=self._own_map_refused,
            )
            if config.sharing.enabled
            else None
        )
        self.merger = Merger(
            self.vehicle_id,
            MergerSettings.from_config(config),
            MergeSources(
                local_snapshot=self.known_snapshot,
                received_maps=self._received_maps,
                local_version=lambda: self.mapper.version,
                peer_results=self._peer_results,
                publish_results=self._publish_results,
                published_version=lambda v: map_versions.compose(self.epoch, v),
                awaited_maps=None if self.sharing is None else self.sharing.awaited_maps,
                peers_alive=None if self.sharing is None else self.sharing.vehicles_alive,
            ),
            self.budget,
            merge_fn=self.merge_fn,
            progress=self.progress,
            start_error=self.merge_start_error,
        )
        self.obstacles = self._make_obstacles() if obstacles_on(config) else None
        self.viewer = None
        self.control = ControlServer(
            config.daemon.control_socket,
            {
                "status": self.handle_status,
                "peers": self.handle_peers,
                "merge-now": self.handle_merge_now,
                "dump-map": self.handle_dump_map,
            },
            max_clients=config.daemon.control_max_clients,
            timeout_s=config.daemon.control_timeout_s,
            max_reply_buffer_bytes=control_reply_buffer(self.budget),
            quick_commands=("status", "peers"),
        )
        self.control.on_thread_start = lambda: self.priorities.apply("control")
        self.watchdog = WatchdogPinger(self.notifier, self.healthy)
        self._stop = threading.Event()
        self._sharing_error: str | None = None
        self.stop_reason = ""
        self._threads: list[threading.Thread] = []
        self._local_message: tuple[int, bytes] | None = None
        self._local_grid: OccupancyGrid | None = None
        """The snapshot _local_message encodes (kept for the sharing delta ledger, never changed)."""
        self._message_lock = threading.Lock()
        self._published_version = 0
        self._saved_versions: dict[str, int] = {"local": self.mapper.version}  # a resumed map is on disk
        self._snapshot_cells = 0
        """Cells of the last known-box snapshot of the local map (what a merge decodes of it)."""
        self._received_restored = False
        """Received maps were restored from their checkpoints: those not held since may be removed."""
        self._origin_saved = self.link.odometry.origin_enu is not None
        self._next_checkpoint = time.monotonic() + (config.daemon.checkpoint_period_s or float("inf"))
        self._next_status = 0.0
        self._next_memory = 0.0
        self._next_log = time.monotonic() + LOG_PERIOD_S

    # ------------------------------------------------------------------------------ building
    def _make_camera(self):
        source = self.config.camera.source
        if source.startswith("realsense"):
            serial = source.partition(":")[2] or None
            return RealSenseSource(self.link.fc_time_at, self.slot, self.config.camera.realsense,
                                   serial=serial)
        address = source[len("socket:") :] if source.startswith("socket:") else source
        cfg = SocketSourceConfig(
            address=address,
            max_payload_bytes=self.config.camera.max_payload_bytes,
            stall_timeout_s=self.config.camera.stall_timeout_s,
        )
        # FC reboots reset its time reference; host-monotonic stamps go through the link's clock fit
        return SocketDepthSource(cfg, self.slot, fc=self.link, host_to_fc=self.link.fc_time_at)

    def _make_mapper(self) -> Mapper:
        """A Mapper on the newest valid local checkpoint (and its map frame), or on an empty grid."""
        cfg = self.config.mapping
        cap = local_grid_cap(self.config, self.budget)
        if cap < 40 * 40 * 20:
            log.error(
                "memory budget of %d MiB leaves %.1f MiB for grids: the local map cannot grow",
                self.config.daemon.memory_mb,
                self.budget.grid_budget / 2**20,
            )
            cap = 40 * 40 * 20
        cfg = replace(cfg, growth=replace(cfg.growth, max_cells=cap))
        grid, version = None, 0
        cp = self.store.load_latest("local")
        origin = self._load_origin()
        if cp is not None:
            problem = None
            if abs(cp.grid.resolution - cfg.resolution) > 1e-9:
                problem = f"resolution {cp.grid.resolution} m is not mapping.resolution {cfg.resolution}"
            elif cp.meta.vehicle_id != self.vehicle_id:
                problem = f"it belongs to vehicle {cp.meta.vehicle_id}, we are {self.vehicle_id}"
            elif cp.grid.size > cap:
                problem = f"{cp.grid.size} cells exceed the local map's budget of {cap} cells"
            elif origin is None:
                problem = f"its map frame ({FRAME_FILE}) is missing"
            if problem:
                log.error("checkpoint %s not resumed: %s; starting an empty map", cp.path.name, problem)
            else:
                grid = OccupancyGrid(cp.grid.cells, cfg.resolution, cp.grid.offset, cfg.growth)
                version = cp.meta.version
                self.link.odometry.origin_enu = origin
                log.info(
                    "local map resumed from %s: version %d, %d known cells, origin FC ENU (%.3f, %.3f, %.3f)",
                    cp.path.name,
                    version,
                    grid.counts().known,
                    *origin,
                )
        mapper = Mapper(cfg, grid)
        if self.versions.reserved and self.versions.reserved >= version:
            # Any version up to the reserve may have been published with other content.
            log.info("local map versions resume above the reserve %d, not at the checkpoint's %d",
                     self.versions.reserved, version)
            version = self.versions.reserved + 1
        mapper.version = version
        self.budget.reserve("local", mapper.grid.size)
        return mapper

    def _make_obstacles(self) -> ObstacleReporter:
        """The OBSTACLE_DISTANCE reporter on the global map overlaid with the live local map."""
        try:
            return ObstacleReporter(
                self.config.obstacles, self.config.mapping.resolution,
                local_map=lambda: (self.mapper.grid, self.mapper.lock),
                global_map=self.merger.global_map,
                pose=lambda: None if self.link.odometry_stale() else self.link.poses.latest(),
                send=self.link.send_obstacle_distance,
                fc_demand=self.link.obstacle_demand.demand,
            )
        except ValueError as e:
            raise StartupError(str(e)) from e

    def _start_viewer(self):
        """The live view's server ([viewer]); foxglove is imported only here, when it is enabled."""
        from coopd.daemon.merger import in_global_map
        from coopd.daemon.viewer import MapViewer

        viewer = MapViewer(
            self.config.viewer,
            local_map=lambda: (self.mapper.grid, self.mapper.lock),
            global_map=self.merger.global_map,
            pose=lambda: None if self.link.odometry_stale() else self.link.poses.latest(),
            peers=lambda: {vid: np.reshape(entry["transform"], (4, 4))
                           for vid, entry in list(self.merger.offsets.items())
                           if in_global_map(entry) and "transform" in entry},
            status=lambda: status_report.build(self),
            vehicle_id=self.vehicle_id,
        )
        try:
            viewer.start()
        except ImportError as e:
            raise StartupError(f"viewer: the foxglove SDK is missing ({e}); pip install 'coopd[viewer]' "
                               "or set [viewer] enabled = false") from e
        except Exception as e:
            raise StartupError(f"viewer on {self.config.viewer.host}:{self.config.viewer.port}: {e}") from e
        return viewer

    def _load_origin(self) -> np.ndarray | None:
        path = self.state_dir / FRAME_FILE
        try:
            with open(path, "rb") as f:
                data = json.loads(f.read(4096))
            origin = np.array(data["origin_fc_enu"], dtype=np.float64)
            if data.get("vehicle_id") != self.vehicle_id or origin.shape != (3,):
                raise ValueError("wrong vehicle or shape")
            if not np.all(np.isfinite(origin)) or np.abs(origin).max() > 1e6:
                raise ValueError("not a finite position")
        except FileNotFoundError:
            return None
        except (OSError, ValueError, KeyError, TypeError) as e:
            log.error("map frame file %s unusable (%s): ignored", path, e)
            return None
        return origin

    def _save_origin(self) -> None:
        origin = self.link.odometry.origin_enu
        if origin is None or self._origin_saved:
            return
        try:
            save_map_frame(self.state_dir, self.vehicle_id, origin)
        except OSError as e:
            log.error("cannot save the map frame to %s: %s", self.state_dir / FRAME_FILE, e)
            return
        self._origin_saved = True

    # ----------------------------------------------------------------------------- lifecycle
    def start(self) -> None:
        """Warm the kernels, resume received maps, start every thread, then READY=1."""
        self._remove_stray_temp_files()
        try:
            self.control.start()
        except (OSError, RuntimeError) as e:
            raise StartupError(f"control socket {self.config.daemon.control_socket}: {e}") from e
        self._spawn("coopd-mavlink", "mavlink", self.link.run)
        if isinstance(self.camera, RealSenseSource):
            try:  # a missing module is a broken install; a missing device is waited for (camera thread)
                load_pyrealsense2()
            except CameraUnavailable as e:
                raise StartupError(f"camera.source {self.config.camera.source}: {e}") from e
        self._spawn("coopd-camera", "camera", self.camera.run)
        self._spawn("coopd-mapping", "mapping", self._mapping_loop)
        if self.sharing is not None:
            started = threading.Event()
            self._spawn("coopd-sharing", "sharing", lambda: self._sharing_loop(started))
            if not started.wait(10.0) or self._sharing_error is not None:
                raise StartupError(f"sharing on port {self.config.sharing.port}: {self._sharing_error}")
        self._spawn("coopd-merging", "merging", self.merger.run)
        if self.obstacles is not None:
            self._spawn("coopd-obstacles", "obstacles",
                        lambda: self.obstacles.run(beat=lambda: self.progress.beat("obstacles")))
        if self.config.viewer.enabled or self.config.viewer.record_dir:
            self.viewer = self._start_viewer()
            self._spawn("coopd-viewer", "viewer", self.viewer.run)
        self.watchdog.start()
        self.state = "running"
        self.notifier.ready(self.summary())
        log.info(
            "coopd vehicle %d running (pid %d): MAVLink %s, camera %s, control %s, memory budget %d MiB",
            self.vehicle_id,
            self.pid,
            self.config.vehicle.mavlink,
            self.config.camera.source,
            self.config.daemon.control_socket,
            self.config.daemon.memory_mb,
        )

    def _spawn(self, name: str, role: str, target) -> None:
        def run():
            self.priorities.apply(role)
            try:
                target()
            except Exception:
                log.exception("thread %s ended with an error", name)

        t = threading.Thread(target=run, name=name, daemon=True)
        t.start()
        self._threads.append(t)

    def _warm_up(self) -> None:
        """Load (or compile) the mapping, codec and merging kernels before the budget measures its
        baseline and before the first frame counts against latency."""
        t0 = time.monotonic()
        failed = warm_up_kernels(self.config.mapping, self.vehicle_id, self.merge_fn)
        self.merge_start_error = failed or self.merge_start_error
        log.info("kernels ready in %.1f s", time.monotonic() - t0)

    def _remove_stray_temp_files(self) -> None:
        for name in (FRAME_FILE, VERSION_FILE):
            for p in self.state_dir.glob(f".{name}.*.tmp"):
                try:
                    p.unlink()
                except OSError:
                    pass

    def request_stop(self, reason: str) -> None:
        """Ask run() to return (signal handlers call this; it only sets an event)."""
        if not self._stop.is_set():
            self.stop_reason = reason
            self._stop.set()

    def run(self) -> None:
        """The main loop: health beat, memory ledger, periodic checkpoint and STATUS, until stopped."""
        while not self._stop.is_set():
            now = time.monotonic()
            self.progress.beat("main")
            self.healthy()  # logs a worker that stopped making progress, also without a watchdog
            self.gcs.update(self.health())
            if now >= self._next_memory:
                self._next_memory = now + MEMORY_PERIOD_S
                self._account_memory()
            if now >= self._next_checkpoint:
                self._next_checkpoint = now + self.config.daemon.checkpoint_period_s
                self.checkpoint()
            if now >= self._next_status:
                self._next_status = now + STATUS_PERIOD_S
                self.notifier.status(self.summary())
            if now >= self._next_log:
                self._next_log = now + LOG_PERIOD_S
                log.info("%s", status_report.log_line(self))
            self._stop.wait(MAIN_PERIOD_S)

    def health(self) -> Health:
        """What the FC and GCS are told about (coopd.daemon.gcs): link, odometry, camera, merges."""
        camera = self.camera.status() if hasattr(self.camera, "status") else {}
        age = camera.get("last_frame_age_s")
        merged = frozenset(vid for vid, o in list(self.merger.offsets.items()) if in_global_map(o))
        return Health(
            link_ok=self.link.state == "ok",
            odometry_fresh=not self.link.odometry_stale(),
            camera_fresh=age is not None and age <= self.config.camera.stall_timeout_s,
            camera_age_s=age,
            merged=merged,
            frame_note=self.link.frames.note(),
        )

    def shutdown(self) -> None:
        """Stop every stage, write the final checkpoint, remove the control socket."""
        t0 = time.monotonic()
        self.state = "stopping"
        log.info("stopping (%s)", self.stop_reason or "requested")
        self.notifier.stopping("stopping: writing the final checkpoint")
        self._stop.set()
        self.watchdog.stop()
        self.merger.stop()
        if self.obstacles is not None:
            self.obstacles.stop()
        if self.viewer is not None:
            self.viewer.stop()
        self.camera.stop()
        self.link.stop()
        for t in self._threads:
            if t.name in ("coopd-mapping", "coopd-camera", "coopd-mavlink", "coopd-obstacles"):
                t.join(SHUTDOWN_JOIN_S)
        self.checkpoint()
        if self.sharing is not None:
            self.sharing.stop()
        self.control.stop()
        for t in self._threads:
            t.join(SHUTDOWN_JOIN_S)
        self.mapper.close()
        self.notifier.close()
        self.state = "stopped"
        log.info("stopped in %.1f s", time.monotonic() - t0)

    # ------------------------------------------------------------------------------- mapping
    def _mapping_loop(self) -> None:
        """Take the newest frame (older ones were replaced and counted), pose it, integrate it."""
        while not self._stop.is_set():
            self.progress.beat("mapping")
            frame = self.slot.take(timeout=0.2)
            if frame is None:
                continue
            associated = self.associator.associate(frame)
            if associated is None:
                if self.associator.last_skip == "frame_paused":  # the FC's frame moved: re-anchor it
                    with self.progress.working("mapping"):
                        self.reanchor.offer(frame)
                continue
            try:
                self.mapper.integrate(
                    associated.depth, associated.intrinsics, associated.camera_pose, associated.stamp
                )
            except FrameRejected:
                continue  # counted by the Mapper
            except Exception:  # a bug on one frame must not end mapping; counted, shown in status
                self.mapping_errors += 1
                if self.mapping_errors <= 3 or self.mapping_errors % 100 == 0:
                    log.exception("mapping error on frame %d (%d so far)", frame.seq, self.mapping_errors)
                continue
            self.frames_mapped += 1
            self.latency_s.append(time.monotonic() - frame.received_local)

    # ------------------------------------------------------------------------------- sharing
    def _sharing_loop(self, started: threading.Event) -> None:
        """Start the sharing service from this thread (its threads inherit the priority), restore the
        received maps from their checkpoints, then publish the local map whenever it changed."""
        try:
            self.sharing.start()
        except OSError as e:
            self._sharing_error = str(e)
            started.set()
            return
        with self.progress.working("sharing"):  # decoding many checkpoints takes a while
            self._restore_received()
        self._received_restored = True
        started.set()
        while not self._stop.wait(PUBLISH_PERIOD_S):
            self.progress.beat("sharing")
            self._maybe_new_epoch()
            version = self.mapper.version
            if version >= 1 and version > self._published_version:
                with self.progress.working("sharing"):  # encoding a big map takes a while
                    self._publish_local()

    def _publish_local(self) -> None:
        v, message, grid = self._local_map()  # the grid too: the sharing delta ledger hashes it
        self.versions.ensure(v)
        wire_version = map_versions.compose(self.epoch, v)
        try:
            self.sharing.publish(with_version(message, wire_version), wire_version, grid)
            self._published_version = v
        except ValueError as e:
            log.error("publishing local map v%d refused: %s", wire_version, e)

    def _own_map_refused(self, peer_vid: int, version: int, status: int) -> None:
        """A peer refused our map's version or holds a newer one of ours we never sent (sender thread)."""
        self._own_refusal = (peer_vid, version, status)

    def _maybe_new_epoch(self) -> None:
        """After a peer refused our version (a forged newer one pins us there), publish the map again
        under a new epoch: the clock's seconds, so it passes any version forged within the receivers'
        clock-skew bound once that much time went by."""
        refusal = self._own_refusal
        if refusal is None or time.monotonic() - self._epoch_at < NEW_EPOCH_MIN_S \
                or int(time.time()) <= self.epoch:  # epochs never run ahead of the clock
            return
        self._own_refusal = None
        self.epoch = self.versions.new_epoch()
        self._epoch_at = time.monotonic()
        self._published_version = 0
        peer, version, status = refusal
        why = "refused the version of" if status == ACK_VERSION else "holds a version we never sent of"
        log.warning("vehicle %d %s our map v%d: publishing it again in a new version epoch %d", peer, why,
                    version, self.epoch)

    def _restore_received(self) -> None:
        for name in self.store.names():
            if not name.startswith("peer-"):
                continue
            cp = self.store.load_latest(name, max_cells=self.mergeable_cells())
            if cp is None:
                continue
            why = map_versions.refusal(cp.meta.version, None,
                                       max_ahead_s=self.config.sharing.max_clock_skew_s)
            if why is not None:
                log.warning("received map %s not restored: %s", cp.path.name, why)
                continue
            data = encode_map(cp.grid, cp.meta)
            summary = MessageSummary(cp.meta.vehicle_id, cp.meta.version, len(data), cp.grid.size)
            try:
                if self.sharing.received.offer(summary, data, via=None):
                    self._saved_versions[name] = cp.meta.version
                    log.info("received map of vehicle %d v%d restored from %s", cp.meta.vehicle_id,
                             cp.meta.version, cp.path.name)
            except Exception as e:  # StoreFull: the budget shrank since it was saved
                log.warning("received map %s not restored: %s", cp.path.name, e)

    def _on_map_received(self, vehicle_id: int, version: int) -> None:
        if self.config.merging.on_receive:
            self.merger.on_map(vehicle_id, version)

    def _peer_results(self) -> list:
        return [] if self.sharing is None else self.sharing.results.all()

    def _publish_results(self, message: MergeResultMessage) -> None:
        """Our validated merge results, offered to peers (wire type 2) if sharing is on."""
        if self.sharing is not None:
            self.sharing.publish_result(encode_merge_result(message), message.version)

    def _received_maps(self) -> list:
        return [] if self.sharing is None else self.sharing.received.all()

    def known_snapshot(self) -> tuple[OccupancyGrid, int]:
        """A copy of the local map cropped to its known cells (same keys, so the same frame) and its
        version. The grid grows by whole steps on both sides and is mostly unknown (a 40 m corridor:
        32 M cells, 4 M of them known); only the known box is copied, under the mapping lock."""
        with self.mapper.lock:
            grid, version = self.mapper.grid.shrunk(pad=SNAPSHOT_PAD_CELLS), self.mapper.version
        self._snapshot_cells = grid.size
        return grid, version

    def mergeable_cells(self) -> int:
        """The largest received map, in cells, this daemon could merge within its memory budget."""
        return min(self.config.sharing.max_map_cells, mergeable_cells(self.budget.grid_budget,
                                                                      self._snapshot_cells))

    def local_message(self) -> tuple[int, bytes]:
        """(version, encoded local map), encoded again only when the map changed."""
        version, message, _ = self._local_map()
        return version, message

    def _local_map(self) -> tuple[int, bytes, OccupancyGrid]:
        """(version, encoded local map, the snapshot it encodes), made again only when the map changed."""
        with self._message_lock:
            cached = self._local_message
            if cached is None or cached[0] != self.mapper.version:
                grid, version = self.known_snapshot()
                message = encode_map(grid, MapMeta(self.vehicle_id, version, time.time()))
                self._local_message = (version, message)
                self._local_grid = grid
            return (*self._local_message, self._local_grid)

    # -------------------------------------------------------------------- persistence, memory
    def checkpoint(self) -> None:
        """Save the local map and every received map that changed since their last checkpoint."""
        self._save_origin()
        if self.mapper.version > self._saved_versions.get("local", 0) and self._origin_saved:
            version, message = self.local_message()
            if self.store.save_message("local", message) is not None:
                self._saved_versions["local"] = version
        held = set()
        for m in self._received_maps():
            name = f"peer-{m.vehicle_id}"
            held.add(name)
            if m.version > self._saved_versions.get(name, -1):
                if self.store.save_message(name, m.data) is not None:
                    self._saved_versions[name] = m.version
        if self._received_restored:  # maps evicted from the store must not come back after a restart
            for name in [n for n in self.store.names() if n.startswith("peer-") and n not in held]:
                if self.store.remove(name):
                    self._saved_versions.pop(name, None)
                    log.info("checkpoint of %s removed: its map is no longer held", name)

    def _account_memory(self) -> None:
        """Every grid in the ledger: local (cells), received (compressed bytes); RSS against the budget."""
        self.rss_watch.check(self.budget.rss())
        self.budget.reserve("local", self.mapper.grid.size)
        if self.sharing is not None:
            self.budget.reserve("sharing-deltas", self.sharing.delta_bytes)
        held = set()
        for m in self._received_maps():
            held.add(f"received:{m.vehicle_id}")
            self.budget.reserve(f"received:{m.vehicle_id}", len(m.data))
        for name in self.budget.names():
            if name.startswith("received:") and name not in held:
                self.budget.release(name)

    # -------------------------------------------------------------------------------- health
    def healthy(self) -> bool:
        """True while every watched thread makes progress (WorkerProgress); a thread that stops, and
        one that starts again, is logged once."""
        stalled = self.progress.stalled()
        with self._health_lock:
            before, self._stalled = self._stalled, stalled
        for name in stalled.keys() - before.keys():
            log.error("thread %s %s: not healthy, the systemd watchdog is no longer fed", name, stalled[name])
        for name in before.keys() - stalled.keys():
            log.info("thread %s makes progress again: healthy", name)
        return not stalled

    def stalled_threads(self) -> dict[str, str]:
        """The watched threads not making progress at the last health check, with the reason."""
        with self._health_lock:
            return dict(self._stalled)

    def summary(self) -> str:
        return status_report.summary(self)

    # ------------------------------------------------------------------------------ commands
    def handle_status(self, args: dict) -> dict:
        try:
            sections = status_report.check_sections(args.get("sections"))
        except ValueError as e:
            raise CommandFailed(str(e)) from None
        return status_report.build(self, sections)

    def handle_peers(self, args: dict) -> dict:
        return {"peers": status_report.build(self, frozenset({"peers"}))["peers"]}

    def handle_merge_now(self, args: dict) -> dict:
        return self.merger.merge_now(MERGE_NOW_TIMEOUT_S)

    def handle_dump_map(self, args: dict) -> BlobReply:
        which = args.get("map")
        if which == "local":
            version, message = self.local_message()
            return BlobReply({"map": "local", "version": version}, message)
        if which == "global":
            merged = self.merger.global_map()
            if merged is None:
                version, message = self.local_message()
                note = status_report.global_note(self)
                return BlobReply({"map": "global", "version": version, "note": note}, message)
            grid, meta = merged
            return BlobReply({"map": "global", "version": meta.version}, encode_map(grid.shrunk(), meta))
        if which == "peer":
            vid = args.get("vehicle_id")
            if not isinstance(vid, int) or isinstance(vid, bool) or not 1 <= vid <= 255:
                raise CommandFailed("peer maps are named by a vehicle id 1..255")
            stored = None if self.sharing is None else self.sharing.received.get(vid)
            if stored is None:
                raise CommandFailed(f"no map received from vehicle {vid}")
            return BlobReply({"map": f"peer:{vid}", "version": stored.version}, stored.data)
        raise CommandFailed("map must be local, global or peer (with vehicle_id)")


def install_signal_handlers(daemon: Daemon) -> None:
    """SIGTERM/SIGINT stop the daemon (checkpoint written); SIGHUP is logged and ignored."""

    def stop(signum, _frame):
        daemon.request_stop(signal.Signals(signum).name)

    signal.signal(signal.SIGTERM, stop)
    signal.signal(signal.SIGINT, stop)
    signal.signal(signal.SIGHUP, lambda *_: log.info("SIGHUP ignored: restart coopd to reload the config"))

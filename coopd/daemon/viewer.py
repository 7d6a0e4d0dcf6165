"""The viewer thread: a live view of the map for the Foxglove app ([viewer], the viewer extra).

The Foxglove SDK serves the Foxglove WebSocket protocol; coopd only logs messages to its channels:

    /map     foxglove.SceneUpdate: the occupied cells as cubes, one entity per brick of BRICK_EDGE^3
             cells (id "brick X Y Z"); each tick sends only the bricks whose cells changed, and a
             brick that became empty is deleted, so a 1 M-cell map costs what changes, not its size.
             Runs of occupied cells along x are one cube each.
    /tf      foxglove.FrameTransforms: map -> base_link (this vehicle's newest pose) and
             map -> vehicle_N (each merged peer's map frame, from its accepted transform).
    /track   foxglove.PosesInFrame: this vehicle's last TRACK_POSES poses, TRACK_STEP_M apart.
    /status  JSON: what `coopctl status` shows.

The same channels can be recorded to an MCAP file ([viewer] record_dir) by the SDK. A channel
nobody receives (no subscribed client, no recording) is not computed. The map is read the way the
obstacles thread reads it: the merger's installed global map is never changed (a merge installs a
new one), and the live local map is read under the mapping lock only when the view needs it (no
global map yet, or colour = "source"), both a slab of BRICK_EDGE x-layers at a time. The foxglove
module is imported only when the viewer starts, so the drone install runs without it.
"""

import colorsys
import hashlib
import ipaddress
import json
import logging
import os
import threading
import time
from collections import deque
from collections.abc import Callable

import numpy as np

from coopd.daemon.config import ViewerConfig
from coopd.daemon.threads import run_at_rate
from coopd.geometry import matrix_to_quat
from coopd.grid import OCCUPIED_THRESHOLD
from coopd.grid.sectors import read_window

log = logging.getLogger("coopd.daemon")

BRICK_EDGE = 8
"""Cells along each side of a brick: the unit the map is re-sent in when one of its cells changes
(8 sent 20 % fewer bytes than 16 while a 1 M-cell map was explored, and kept the peak under 1 Mbit/s:
scripts/bench viewer)."""
BRICKS_PER_MESSAGE = 256
"""Bricks in one /map message (a few hundred kB for walls; a whole map takes several messages)."""
BACKLOG_MESSAGES = 64
"""Messages the server queues per client (16 s at 1 Hz): a stalled client costs a bounded amount of
memory; the SDK drops its oldest data then, and reconnecting gets the whole map again."""
TRACK_POSES = 300
"""Poses kept in the track; the whole track is one message per tick (about 70 bytes a pose)."""
TRACK_STEP_M = 0.5
"""A pose joins the track once the vehicle moved this far from the last one (hovering adds none)."""
HEIGHT_PERIOD_M = 4.0
"""Colour by height cycles through the hues every this many metres (a fixed scale: growing the map
never recolours, hence never re-sends, the bricks already sent)."""
OWN, PEER = 1, 2
"""Cell labels when coloured by source: occupied in this vehicle's local map, or only in peers'."""
SOURCE_COLOURS = {OWN: (0.15, 0.45, 1.0), PEER: (1.0, 0.55, 0.1)}


# ------------------------------------------------------------------------------ bricks (pure)
def brick_views(labels: np.ndarray, offset, edge: int = BRICK_EDGE) -> tuple[np.ndarray, np.ndarray]:
    """(brick keys (n, 3), blocks (n, edge, edge, edge)) of the bricks holding a non-zero label.

    Bricks are aligned on absolute cell keys (brick key = floor(cell key / edge)), so they stay the
    same bricks when the grid grows and its offset moves."""
    offset = np.asarray(offset, dtype=np.int64)
    first = np.floor_divide(offset, edge)
    pad_lo = offset - first * edge
    padded_shape = -(-(pad_lo + np.asarray(labels.shape)) // edge) * edge
    padded = np.zeros(tuple(int(s) for s in padded_shape), dtype=labels.dtype)
    padded[pad_lo[0]:pad_lo[0] + labels.shape[0], pad_lo[1]:pad_lo[1] + labels.shape[1],
           pad_lo[2]:pad_lo[2] + labels.shape[2]] = labels
    n = padded_shape // edge
    blocks = padded.reshape(n[0], edge, n[1], edge, n[2], edge).transpose(0, 2, 4, 1, 3, 5)
    nonempty = np.argwhere(blocks.any(axis=(3, 4, 5)))
    return nonempty + first, blocks[tuple(nonempty.T)]


def runs_along_x(block: np.ndarray) -> np.ndarray:
    """Runs of equal non-zero labels along x in a block: rows (x0, y, z, length, label), block keys."""
    e = block.shape[0]
    rows = np.zeros((block.shape[1] * block.shape[2], e + 1), dtype=np.int16)
    rows[:, :e] = block.transpose(1, 2, 0).reshape(-1, e)
    seq = rows.ravel()
    before = np.concatenate(([0], seq[:-1]))
    after = np.concatenate((seq[1:], [0]))
    starts = np.flatnonzero((seq != 0) & (seq != before))
    ends = np.flatnonzero((seq != 0) & (seq != after))
    row, x0 = np.divmod(starts, e + 1)
    y, z = np.divmod(row, block.shape[2])
    return np.stack([x0, y, z, ends - starts + 1, seq[starts]], axis=1).astype(np.int64)


class BrickTracker:
    """Which bricks changed since the last call: a digest per non-empty brick (bounded by the map's
    size: one per BRICK_EDGE^3 cells at most)."""

    def __init__(self, edge: int = BRICK_EDGE):
        self.edge = edge
        self.digests: dict[tuple[int, int, int], bytes] = {}

    def changes(self, views, everything: bool = False):
        """(changed {brick key: block}, emptied [brick keys]) over `views`, the (keys, blocks) of
        brick_views for the whole map (in slabs: the brick keys of two never overlap); everything:
        every non-empty brick."""
        digests, changed = {}, {}
        for keys, blocks in views:
            for key, block in zip(map(tuple, keys.tolist()), blocks, strict=True):
                digest = hashlib.blake2b(block.tobytes(), digest_size=16).digest()
                digests[key] = digest
                if everything or self.digests.get(key) != digest:
                    changed[key] = block
        emptied = [k for k in self.digests if k not in digests]
        self.digests = digests
        return changed, emptied

    def reset(self) -> None:
        self.digests = {}


def labels_of(cells: np.ndarray, local: np.ndarray | None, threshold: int = OCCUPIED_THRESHOLD,
              by_source: bool = False) -> np.ndarray:
    """Cell labels of the view: 0 not occupied, OWN or PEER. `local` is the local map read over the
    same key box (or None); by height every occupied cell is OWN (the label is not a colour)."""
    occupied = cells >= threshold
    labels = occupied.astype(np.int8)
    if by_source:
        own = occupied & (local >= threshold) if local is not None else np.zeros_like(occupied)
        labels[occupied & ~own] = PEER
    return labels


def height_colour(z_m: float) -> tuple[float, float, float]:
    """A hue per height, cycling every HEIGHT_PERIOD_M metres."""
    return colorsys.hsv_to_rgb((z_m / HEIGHT_PERIOD_M) % 1.0, 0.85, 0.95)


def brick_cubes(key, block: np.ndarray, resolution: float, edge: int = BRICK_EDGE,
                by_source: bool = False) -> list[tuple[tuple, tuple, tuple]]:
    """(centre m, size m, rgb) of the cubes a brick is drawn with: one per run along x."""
    origin = np.asarray(key, dtype=np.int64) * edge
    cubes = []
    for x0, y, z, length, label in runs_along_x(block).tolist():
        cx = (origin[0] + x0 + (length - 1) / 2.0) * resolution
        cy, cz = (origin[1] + y) * resolution, (origin[2] + z) * resolution
        rgb = SOURCE_COLOURS[label] if by_source else height_colour(cz)
        cubes.append(((cx, cy, cz), (length * resolution, resolution, resolution), rgb))
    return cubes


def brick_id(key) -> str:
    return "brick {} {} {}".format(*key)


def is_loopback(host: str) -> bool:
    return ipaddress.ip_address(host).is_loopback


def recording_path(directory: str, vehicle_id: int, now_s: float) -> str:
    """DIR/coopd-vehicle<ID>-<UTC time>.mcap, a new name for every start (an existing file is kept)."""
    stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime(now_s))
    os.makedirs(directory, mode=0o750, exist_ok=True)
    base = os.path.join(directory, f"coopd-vehicle{vehicle_id}-{stamp}")
    path, n = base + ".mcap", 1
    while os.path.exists(path):
        n += 1
        path = f"{base}-{n}.mcap"
    return path


def url_of(host: str, port) -> str:
    """ws://HOST:PORT, an IPv6 address in brackets."""
    return f"ws://[{host}]:{port}" if ":" in host else f"ws://{host}:{port}"


# --------------------------------------------------------------------------------------- thread
class MapViewer:
    """Owns the Foxglove server, its channels and the brick tracker; run() is the coopd-viewer loop.

    local_map() -> (grid, lock); global_map() -> the merger's (grid, meta) or None; pose() -> the
    newest PoseSample or None; peers() -> {vehicle id: 4x4 transform of its map frame into ours};
    status() -> a JSON-able dict."""

    def __init__(self, config: ViewerConfig, local_map: Callable, global_map: Callable, pose: Callable,
                 peers: Callable, status: Callable, threshold: int = OCCUPIED_THRESHOLD, vehicle_id: int = 0):
        self.config = config
        self.local_map, self.global_map, self.pose, self.peers, self.status_of = (
            local_map, global_map, pose, peers, status)
        self.threshold = threshold
        self.by_source = config.colour == "source"
        self.tracker = BrickTracker()
        self.track: deque = deque(maxlen=TRACK_POSES)
        self.counters = {"ticks": 0, "bricks_sent": 0, "bricks_deleted": 0, "full_sends": 0, "errors": 0}
        self.port: int | None = None
        self.vehicle_id = vehicle_id
        self.recording: str | None = None
        self.recording_bytes = 0
        self.recording_stopped: str | None = None
        self._writer = None
        self._resend = threading.Event()
        self._stop = threading.Event()
        self._server = None
        self._context = None
        self._channels = None

    # --------------------------------------------------------------------------- server
    def start(self) -> None:
        """Start the WebSocket server if enabled and the recording if record_dir is set (raises
        ImportError without the viewer extra, OSError if the address is taken or the file cannot be
        made); a client subscribing to /map gets every brick on the next tick."""
        import foxglove
        from foxglove.channels import FrameTransformsChannel, PosesInFrameChannel, SceneUpdateChannel
        from foxglove.websocket import ServerListener

        viewer = self

        class Listener(ServerListener):
            def on_subscribe(self, client, channel):
                if channel.topic == "/map":
                    viewer.resend_all()

        context = self._context = foxglove.Context()  # kept: the channels leave it when it is freed
        self._channels = {
            "map": SceneUpdateChannel("/map", context=context),
            "tf": FrameTransformsChannel("/tf", context=context),
            "track": PosesInFrameChannel("/track", context=context),
            "status": foxglove.Channel("/status", message_encoding="json", context=context),
        }
        if self.config.record_dir:
            self.recording = recording_path(self.config.record_dir, self.vehicle_id, time.time())
            self._writer = foxglove.open_mcap(self.recording, context=context)
            log.info("viewer: recording to %s (stops at %d MiB)", self.recording, self.config.record_max_mb)
        if not self.config.enabled:
            return
        self._server = foxglove.start_server(name="coopd", host=self.config.host, port=self.config.port,
                                             server_listener=Listener(), context=context,
                                             message_backlog_size=BACKLOG_MESSAGES)
        self.port = self._server.port
        if not is_loopback(self.config.host):
            log.warning("viewer: listening on %s:%d, not loopback: the Foxglove protocol has no "
                        "authentication, anyone who reaches this address sees the map",
                        self.config.host, self.port)
        log.info("viewer: %s at %.1f Hz, colour by %s", url_of(self.config.host, self.port),
                 self.config.rate_hz, self.config.colour)

    def resend_all(self) -> None:
        """Send every brick on the next tick (a client that subscribes has none of them)."""
        self._resend.set()

    def subscribed(self, topics, timeout_s: float) -> bool:
        """Wait until every topic has a receiver (tests and the bench: a tick skips the others)."""
        by_topic = {"/" + name: channel for name, channel in self._channels.items()}
        deadline = time.monotonic() + timeout_s
        while not all(by_topic[t].has_sinks() for t in topics):
            if time.monotonic() > deadline:
                return False
            time.sleep(0.01)
        return True

    def close(self) -> None:
        if self._server is not None:
            self._server.stop()
            self._server = None
        self._stop_recording(None)

    def _stop_recording(self, reason: str | None) -> None:
        """Close the MCAP file (it is complete and readable from then on)."""
        if self._writer is None:
            return
        self._writer.close()
        self._writer = None
        self.recording_bytes = os.path.getsize(self.recording)
        if reason:
            self.recording_stopped = reason
            log.warning("viewer: recording %s stopped at %.1f MiB: %s", self.recording,
                        self.recording_bytes / 2**20, reason)

    def _check_recording(self) -> None:
        if self._writer is None:
            return
        self.recording_bytes = os.path.getsize(self.recording)
        if self.recording_bytes >= self.config.record_max_mb * 2**20:
            self._stop_recording(f"record_max_mb {self.config.record_max_mb} reached")

    # --------------------------------------------------------------------------- one tick
    def view_slabs(self):
        """(resolution, brick views slab by slab) of the view: the global map, or the local map before
        a merge. A slab is BRICK_EDGE layers along x, so what a tick holds at once is a slab's labels,
        not a map's; the local map is read a slab at a time under the mapping lock."""
        merged = self.global_map()
        grid, lock = self.local_map()
        if merged is None:
            with lock:
                lo, hi = grid.key_bounds()
                resolution = grid.resolution
        else:
            lo, hi = merged[0].key_bounds()
            resolution = merged[0].resolution
        return resolution, self._slabs(None if merged is None else merged[0], grid, lock, lo, hi)

    def _slabs(self, view, grid, lock, lo, hi):
        edge = self.tracker.edge
        for x0 in range(int(lo[0]) // edge * edge, int(hi[0]) + 1, edge):
            slab_lo = (max(x0, int(lo[0])), int(lo[1]), int(lo[2]))
            slab_hi = (min(x0 + edge - 1, int(hi[0])), int(hi[1]), int(hi[2]))
            local = None
            if view is None or self.by_source:
                with lock:
                    local = read_window(grid, slab_lo, slab_hi)
            cells = local if view is None else read_window(view, slab_lo, slab_hi)
            yield brick_views(labels_of(cells, local, self.threshold, self.by_source), slab_lo, edge)

    def map_update(self, everything: bool = False) -> list:
        """The SceneUpdates of the bricks that changed (all of them if everything), at most
        BRICKS_PER_MESSAGE bricks each, so no message grows with the map."""
        from foxglove.messages import (
            Color,
            CubePrimitive,
            Pose,
            Quaternion,
            SceneEntity,
            SceneEntityDeletion,
            SceneEntityDeletionType,
            SceneUpdate,
            Vector3,
        )

        resolution, slabs = self.view_slabs()
        changed, emptied = self.tracker.changes(slabs, everything)
        entities = []
        for key, block in changed.items():
            cubes = [CubePrimitive(pose=Pose(position=Vector3(x=c[0], y=c[1], z=c[2]),
                                             orientation=Quaternion(w=1.0)),
                                   size=Vector3(x=s[0], y=s[1], z=s[2]), color=Color(r=r, g=g, b=b, a=1.0))
                     for c, s, (r, g, b) in brick_cubes(key, block, resolution, self.tracker.edge,
                                                        self.by_source)]
            entities.append(SceneEntity(frame_id="map", id=brick_id(key), cubes=cubes))
        deletions = [SceneEntityDeletion(type=SceneEntityDeletionType.MatchingId, id=brick_id(k))
                     for k in emptied]
        self.counters["bricks_sent"] += len(entities)
        self.counters["bricks_deleted"] += len(deletions)
        n = BRICKS_PER_MESSAGE
        updates = [SceneUpdate(deletions=deletions[i:i + n]) for i in range(0, len(deletions), n)]
        return updates + [SceneUpdate(entities=entities[i:i + n]) for i in range(0, len(entities), n)]

    def frames(self):
        """FrameTransforms map -> base_link and map -> vehicle_N; the pose and its position for the track."""
        from foxglove.messages import FrameTransform, FrameTransforms, Pose, Quaternion, Vector3

        transforms, pose, at = [], None, None
        sample = self.pose()
        if sample is not None:
            p, (w, x, y, z) = sample.position, (float(v) for v in sample.quaternion)
            position = Vector3(x=float(p[0]), y=float(p[1]), z=float(p[2]))
            rotation = Quaternion(x=x, y=y, z=z, w=w)
            pose = Pose(position=position, orientation=rotation)
            at = np.array(p, dtype=np.float64)
            transforms.append(FrameTransform(parent_frame_id="map", child_frame_id="base_link",
                                             translation=position, rotation=rotation))
        for vehicle_id, t in sorted(self.peers().items()):
            t = np.asarray(t, dtype=np.float64).reshape(4, 4)
            w, x, y, z = (float(v) for v in matrix_to_quat(t[:3, :3]))
            transforms.append(FrameTransform(parent_frame_id="map", child_frame_id=f"vehicle_{vehicle_id}",
                                             translation=Vector3(x=t[0, 3], y=t[1, 3], z=t[2, 3]),
                                             rotation=Quaternion(x=x, y=y, z=z, w=w)))
        return FrameTransforms(transforms=transforms), pose, at

    def tick(self) -> None:
        """One update of every channel someone receives (a client subscribed to it, or the recording):
        with nobody watching, the map is not even read."""
        from foxglove.messages import PosesInFrame

        channels = self._channels
        if channels["map"].has_sinks():
            everything = self._resend.is_set()
            self._resend.clear()
            try:
                for update in self.map_update(everything):
                    channels["map"].log(update)
            except Exception:
                self.tracker.reset()  # what the receivers hold is unknown now: send them every brick
                self.resend_all()
                raise
            self.counters["full_sends"] += everything
        else:
            self.tracker.reset()  # nobody holds the bricks: the next subscriber gets all of them
        transforms, pose, at = self.frames()
        if channels["tf"].has_sinks():
            channels["tf"].log(transforms)
        if pose is not None and (not self.track or np.linalg.norm(at - self.track[-1][0]) >= TRACK_STEP_M):
            self.track.append((at, pose))
        if channels["track"].has_sinks():
            channels["track"].log(PosesInFrame(frame_id="map", poses=[p for _, p in self.track]))
        if channels["status"].has_sinks():
            channels["status"].log(json.dumps(self.status_of(), default=str).encode())
        self.counters["ticks"] += 1
        self._check_recording()

    def run(self) -> None:
        """Tick every 1/rate_hz s until stop(); an error on one tick is logged (first three) and counted."""
        run_at_rate(self.tick, self.config.rate_hz, self._stop, self.counters, "viewer")
        self.close()

    def stop(self) -> None:
        self._stop.set()

    def status(self) -> dict:
        served = self.port is not None
        return {"enabled": True, "url": url_of(self.config.host, self.port) if served else None,
                "rate_hz": self.config.rate_hz, "colour": self.config.colour,
                "bricks": len(self.tracker.digests), **self.counters,
                "recording": None if self.recording is None else {
                    "path": self.recording, "bytes": self.recording_bytes, "open": self._writer is not None,
                    "stopped": self.recording_stopped}}


"""The sharing component the daemon uses: serve, discover, share on update (thesis §5.2),
keep the newest received map per vehicle, and report per-peer stats.

    svc = SharingService(SharingConfig(vehicle_id=3, peers=("10.42.0.1-10.42.0.20",)))
    svc.start(); svc.publish(encoded_map, version); ... svc.received.get(5); svc.stop()

Messages are opaque serialized maps; `inspect` reads their header (vehicle id, version, size,
cells) and `verify` (optional) fully decodes them within the limits before they are stored.
Merge-result messages (wire type 2, distributed merging) travel the same way and are authenticated
the same way: `publish_result` offers ours, peers' are decoded and kept in `results` (newest per
sender). They are not relayed: only the vehicle that computed a result sends it.
"""

import logging
import queue
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field

from coopd.net import host_port

from . import discovery, mtp, versions
from .peers import VEHICLE_IDS, MessageSummary, PeerTable, ReceivedStore, ResultStore, StoreFull
from .transport import Arrival, MapServer, PeerLink, Rejected, TransportSettings
from .wire_options import DEFAULT_BRICK_EDGE, MSG_MAP_DELTA
from .zenoh_link import ZenohLink, ZenohSettings

log = logging.getLogger("coopd.sharing")

DEFAULT_PORT = 7400
DECODE_BYTES_PER_CELL = 3
"""Memory a full decode of a received map takes per cell, charged to the memory budget while it
runs: the cells (1 B) plus the largest intermediates (planes-zstd: class plane N/4, escape
nibbles up to N/2, raw escapes up to N)."""
DECODE_LEDGER = "sharing-decode"
SENDER_IDLE_S = 1.0
"""A peer's sender thread with nothing to send wakes this often (an update wakes it at once) to mark
the peer seen and notice it gone: well within the two scan periods after which a peer counts as
gone; with 29 peers, waking twice a second was the largest part of an idle drone's CPU."""


@dataclass(frozen=True)
class SharingConfig:
    """Settings of the sharing component (the [sharing] table of coopd.toml)."""

    vehicle_id: int
    listen_host: str = "0.0.0.0"
    port: int = DEFAULT_PORT
    peers: tuple[str, ...] = ()
    """Addresses to scan: '10.42.0.1-10.42.0.20', '10.42.0.7', 'host:7401', 'fd00::7', '[fd00::7]:7401'."""
    peer_ports: tuple[int, ...] = (DEFAULT_PORT,)
    scan_period: float = 2.0
    grace_period: float = 30.0
    """A peer not seen (and not connected) for this long is dropped from the table."""
    relay: bool = False
    """Also forward maps received from others (multi-hop); see docs/sharing.md."""
    relay_delay: float = 1.0
    """A received map is relayed only after this many seconds, so that peers in range of its
    origin get it from the origin first and the relay is not wasted."""
    max_vehicles: int = 256
    """Received maps of at most this many vehicles are held."""
    max_received_bytes: int = 1 << 30
    """Bytes of received (serialized, compressed) maps held at most: part of the memory budget."""
    allowed_vehicles: frozenset[int] = frozenset()
    """If not empty: maps and merge results only of these vehicle ids are accepted."""
    max_epoch_ahead_s: float = versions.MAX_EPOCH_AHEAD_S
    """A received version whose epoch (or a merge result whose µs version) is further in the future
    than this is refused (clock skew allowed between vehicles)."""
    deltas: bool = True
    """Send our map to peers that read deltas as the bricks changed since the version they hold, and
    read peers' deltas (docs/sharing.md, "Deltas"); False: full maps only, both ways."""
    delta_brick_edge: int = DEFAULT_BRICK_EDGE
    """Cells per brick edge of the deltas we send (4, 8, 16, 32 or 64)."""
    transport: TransportSettings = field(default_factory=TransportSettings)
    mtp: bool = True
    """Serve and scan over MTP (TCP)."""
    zenoh: ZenohSettings | None = None
    """Also (or, without mtp, only) publish and receive over Zenoh (zenoh_link); None: not."""


def _notify(callback: Callable[[int, int], None] | None, name: str, summary: MessageSummary) -> None:
    """Tell a consumer what was stored; its bug must not fail the transfer (logged instead)."""
    if callback is None:
        return
    try:
        callback(summary.vehicle_id, summary.version)
    except Exception:
        log.exception("%s callback failed for vehicle %d v%d", name, summary.vehicle_id, summary.version)


def wire_inspect(data) -> MessageSummary:
    """inspect() for real map messages (coopd.sharing.wire)."""
    from . import wire

    if len(data) and data[0] == wire.MSG_MERGE_RESULT:
        vid, version, size = wire.peek_merge_result(data)
        return MessageSummary(vid, version, size, 0, "result")
    if len(data) and data[0] == MSG_MAP_DELTA:
        from . import delta

        info = delta.peek_delta(data)
        return MessageSummary(info.vehicle_id, info.map_version, info.total_size, info.cells, "delta",
                              info.base_version)
    info = wire.peek(data)
    return MessageSummary(info.vehicle_id, info.map_version, info.total_size, info.cells)


def wire_verifier(max_cells: int, max_bytes: int) -> Callable[[memoryview], None]:
    """verify() for real map messages: decode once within the limits, keep nothing."""
    from . import wire

    limits = wire.DecodeLimits(max_cells=max_cells, max_bytes=max_bytes)

    def verify(message: bytes) -> None:
        wire.decode_map(message, limits)

    return verify


class SharingService:
    """Server + discovery + one sender per peer vehicle; see the module docstring."""

    def __init__(self, config: SharingConfig, inspect: Callable = wire_inspect,
                 verify: Callable | None = None, on_map: Callable | None = None,
                 on_result: Callable[[int, int], None] | None = None, budget=None,
                 cell_cap: Callable[[], int] | None = None,
                 on_own_refused: Callable[[int, int, int], None] | None = None):
        """`budget` (a daemon MemoryBudget, optional): receive buffers and decodes are charged to it.
        `cell_cap` (optional): the largest received map, in cells, this vehicle can merge now; a
        bigger one is refused at receive, before it is decoded or stored."""
        self.config = config
        self._on_own_refused = on_own_refused
        """(peer vehicle, our version, ack status): a peer refused our own map's version (ACK_VERSION) or
        holds a newer one we never sent (ACK_STALE): someone else's version of our map got there
        first, and a new version epoch gets ours through again."""
        self._budget = budget
        self._cell_cap = cell_cap
        self._decoding = threading.Lock()
        """One received map decodes at a time: its memory is charged to the budget while it runs."""
        self.vehicle_id = config.vehicle_id
        self._inspect = inspect
        self._verify = verify
        self._on_map = on_map
        self._on_result = on_result
        self.peers = PeerTable()
        self.received = ReceivedStore(config.max_vehicles, config.max_received_bytes)
        self.results = ResultStore(config.max_vehicles)
        """Peers' merge results (wire.MergeResultMessage), newest per sender."""
        self.arrivals: queue.Queue = queue.Queue(maxsize=64)
        """(vehicle id, version) of every stored map, for consumers that poll; oldest dropped if full."""
        self._targets = discovery.parse_targets(config.peers, config.peer_ports)
        self._server = MapServer(config.transport, config.vehicle_id, self._accept, self.peers,
                                 config.listen_host, config.port, self._wants, ledger=budget,
                                 deltas=config.deltas)
        self.zenoh = None if config.zenoh is None else ZenohLink(
            config.zenoh, config.vehicle_id, config.transport.swarm_key, inspect, self._accept,
            self.peers.failure, config.transport.max_bytes, ledger=budget)
        self._own: tuple[int, bytes] | None = None
        self._bricks = None
        """The BrickLedger of our published maps (coopd.sharing.delta), once one came with its grid."""
        self._delta_refused_by: set[int] = set()
        """Peers that refused a delta although their hello said they read them: sent full maps only."""
        self._own_result: tuple[int, bytes] | None = None
        self._update = threading.Condition()
        self._stop = threading.Event()
        self._senders: dict[int, _Sender] = {}
        self._busy_targets: set[tuple[str, int]] = set()
        self._self_targets: set[tuple[str, int]] = set()
        self._alias_targets: dict[tuple[str, int], int] = {}
        """Targets that reached a vehicle already served at another address -> that vehicle id."""
        self._backoff: dict[tuple[str, int], tuple[float, int]] = {}
        """Targets whose handshake failed -> (monotonic time of the next try, failures in a row)."""
        self._unnamed_at: dict[tuple[str, int], float] = {}
        """Targets that answered (TCP) but whose handshake failed, and when: a peer whose map may
        still come (awaited_maps); forgotten once a handshake there names the vehicle."""
        self._all_senders: set[_Sender] = set()
        self._lock = threading.Lock()
        self._scanner: threading.Thread | None = None
        self.scans = 0

    # ------------------------------------------------------------------ lifecycle
    @property
    def address(self) -> tuple[str, int] | None:
        """Where the MTP server listens (None without MTP)."""
        return self._server.address if self.config.mtp else None

    def start(self) -> "SharingService":
        if self.config.mtp:
            self._server.start()
            self._scanner = threading.Thread(target=self._scan_loop, name="coopd-share-discovery",
                                             daemon=True)
            self._scanner.start()
        if self.zenoh is not None:
            self.zenoh.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        with self._update:
            self._update.notify_all()
        if self._scanner is not None:
            self._scanner.join(5)
        with self._lock:
            senders = list(self._all_senders)
        for s in senders:
            s.link.close()
        for s in senders:
            s.thread.join(5)
        self._server.stop()
        if self.zenoh is not None:
            self.zenoh.stop()

    # ------------------------------------------------------------------ publishing
    def publish(self, message: bytes, version: int, grid=None) -> None:
        """Offer our latest map; peers get it if `version` is newer than what they have. With `grid` (the
        OccupancyGrid `message` carries, not changed afterwards) and deltas on, peers that read deltas
        get the bricks changed since the version they hold; without, full maps only."""
        if version < 1:
            raise ValueError(f"published versions start at 1, got {version}")
        with self._update:
            if self._own is not None and version < self._own[0]:
                raise ValueError(f"version {version} is older than the published {self._own[0]}")
        bricks = None
        if grid is not None and self.config.deltas:
            from .delta import BrickLedger

            bricks = self._bricks
            if bricks is None or (bricks.latest_version or 0) > version:
                bricks = BrickLedger(self.config.delta_brick_edge)
            if bricks.latest_version != version:  # the same version again: already recorded
                try:
                    bricks.record(grid, version, message)
                except ValueError as e:  # a grid that is not the message's: full maps, never no map
                    log.error("map v%d published without deltas: %s", version, e)
                    bricks = None
        with self._update:
            previous = None if self._own is None else self._own[0]
            self._own = (version, bytes(message))
            self._bricks = bricks
            self._update.notify_all()
        if self.zenoh is not None:  # one delta for everyone: from the version published before
            delta = None if bricks is None or previous is None else bricks.delta_for(previous)
            self.zenoh.publish_map(self._own[1], delta)

    @property
    def delta_bytes(self) -> int:
        """Memory the delta ledger holds: our latest map and its bricks' hashes (for the memory budget)."""
        bricks = self._bricks
        return 0 if bricks is None else bricks.held_bytes

    def own_delta(self, peer_vid: int, version: int) -> bytes | None:
        """Our map at `version` as a delta from the version `peer_vid` is known to hold, or None (full)."""
        bricks = self._bricks
        if bricks is None or bricks.latest_version != version:
            return None
        return bricks.delta_for(self.peers.has_version(peer_vid, self.vehicle_id))

    def publish_result(self, message: bytes, version: int) -> None:
        """Offer our latest merge-result message (wire type 2); peers get it if `version` is newer."""
        if version < 1:
            raise ValueError(f"published versions start at 1, got {version}")
        with self._update:
            if self._own_result is not None and version <= self._own_result[0]:
                raise ValueError(f"result version {version} is not newer than the published "
                                 f"{self._own_result[0]}")
            self._own_result = (version, bytes(message))
            self._update.notify_all()
        if self.zenoh is not None:
            self.zenoh.publish("merge", self._own_result[1])

    def pending_for(self, peer_vid: int) -> list[tuple[int, int, bytes, str]]:
        """(origin, version, message, kind) this peer lacks: our map and merge result, and with relay,
        others' maps."""
        out = []
        own = self._own
        if own is not None and own[0] > self.peers.has_version(peer_vid, self.vehicle_id):
            out.append((self.vehicle_id, own[0], own[1], "map"))
        result = self._own_result
        if result is not None and result[0] > self.peers.has_version(peer_vid, self.vehicle_id, "result"):
            out.append((self.vehicle_id, result[0], result[1], "result"))
        if self.config.relay:
            settled = time.time() - self.config.relay_delay
            for m in self.received.all():
                if m.vehicle_id in (peer_vid, self.vehicle_id) or m.via == peer_vid:
                    continue
                if m.received_at > settled:
                    continue  # picked up by a later wake-up of the sender loop
                if m.version > self.peers.has_version(peer_vid, m.vehicle_id):
                    out.append((m.vehicle_id, m.version, m.data, "map"))
        return out

    def decode(self, vehicle_id: int):
        """(OccupancyGrid, MapMeta) of the stored map of `vehicle_id`, decoded now within the limits
        (received maps rest serialized until the merger asks); None if none is held."""
        from . import wire

        stored = self.received.get(vehicle_id)
        if stored is None:
            return None
        s = self.config.transport
        return wire.decode_map(stored.data, wire.DecodeLimits(max_cells=s.max_cells, max_bytes=s.max_bytes))

    def vehicles_alive(self) -> frozenset[int]:
        """Other vehicles known alive: seen within two scan periods over MTP, or holding a liveliness
        token over Zenoh (only allowed vehicles, when the swarm is restricted)."""
        alive = set(self.peers.alive(2 * self.config.scan_period))
        if self.zenoh is not None:
            alive |= self.zenoh.vehicles_alive()
        allowed = self.config.allowed_vehicles
        if allowed:
            alive &= set(allowed)
        alive.discard(self.vehicle_id)
        return frozenset(alive)

    def awaited_maps(self) -> int:
        """Maps still coming, which a first merge may wait for: peers alive (seen within two scan
        periods over MTP, a liveliness token over Zenoh) whose map we do not hold, and over MTP the
        peers that answered but are not named yet (a handshake under way, or one that failed within
        two scan periods: on a loaded host handshakes time out and are retried)."""
        window = 2 * self.config.scan_period
        alive = self.vehicles_alive()
        now = time.monotonic()
        with self._lock:
            unnamed = {s.target for s in self._all_senders if s.vid is None}
            unnamed |= {t for t, at in self._unnamed_at.items() if now - at <= window}
            unnamed -= self._self_targets | set(self._alias_targets)
        return len(alive - {m.vehicle_id for m in self.received.all()}) + len(unnamed)

    # ------------------------------------------------------------------ receiving
    def _wants(self, origin: int, version: int) -> int:
        """Answer a relay offer: send it (ACK_OK) unless we hold that version or newer (ACK_STALE)."""
        allowed = self.config.allowed_vehicles
        held = self.received.version(origin)
        if origin == self.vehicle_id or origin not in VEHICLE_IDS or (allowed and origin not in allowed) \
                or 0 < version <= held \
                or versions.refusal(version, held if held > 0 else None,
                                    max_ahead_s=self.config.max_epoch_ahead_s) is not None:
            return mtp.ACK_STALE
        return mtp.ACK_OK

    def _accept(self, arrival: Arrival) -> int:
        """Check a complete transfer, store it if newer; Rejected drops it (counted by the server)."""
        s = self.config.transport
        data = arrival.data
        try:
            summary = self._inspect(data)
        except ValueError as e:
            raise Rejected("malformed", f"message header: {e}") from None
        if summary.size > len(data):
            raise Rejected("size", f"message says {summary.size} bytes, its {arrival.blocks} blocks hold "
                                   f"{len(data)}")
        if len(data) - summary.size >= s.block_size:
            raise Rejected("size", f"message of {summary.size} bytes sent in {arrival.blocks} blocks "
                                   f"(more than it needs)")
        if summary.vehicle_id not in VEHICLE_IDS:
            raise Rejected("vehicle_id", f"vehicle id {summary.vehicle_id} is outside "
                                         f"{VEHICLE_IDS.start}..{VEHICLE_IDS.stop - 1}")
        allowed = self.config.allowed_vehicles
        if allowed and summary.vehicle_id not in allowed:
            raise Rejected("not_allowed", f"vehicle {summary.vehicle_id} is not in sharing.allowed_vehicles")
        if summary.cells > s.max_cells:
            raise Rejected("oversize", f"{summary.cells} cells, limit {s.max_cells}")
        if summary.kind == "map" and self._cell_cap is not None:
            cap = self._cell_cap()
            if summary.cells > cap:
                raise Rejected("oversize", f"map of vehicle {summary.vehicle_id} v{summary.version} has "
                                           f"{summary.cells} cells; this vehicle can merge at most {cap} "
                                           f"within its memory budget (refused before decoding)")
        via = arrival.peer_vehicle_id if arrival.peer_vehicle_id is not None else summary.vehicle_id
        if arrival.peer_vehicle_id is not None:
            self._forgive(arrival.address)
        if summary.kind == "result":
            return self._accept_result(arrival, summary, via)
        if summary.kind == "delta" and not self.config.deltas:
            raise Rejected("malformed", "a map delta, but this vehicle reads full maps only (sharing.deltas)")
        nbytes, kind = summary.size, summary.kind  # a delta's own size: what travelled
        if summary.vehicle_id == self.vehicle_id:
            self.peers.received(via, summary.vehicle_id, summary.version, nbytes, arrival.seconds,
                                arrival.address)
            return mtp.ACK_STALE
        held = self.received.version(summary.vehicle_id)
        why = versions.refusal(summary.version, held if held > 0 else None,
                               max_ahead_s=self.config.max_epoch_ahead_s)
        if why is not None:
            raise Rejected("version", f"map of vehicle {summary.vehicle_id}: {why}")
        if summary.version != 0 and summary.version <= held:
            self.peers.received(via, summary.vehicle_id, summary.version, nbytes, arrival.seconds,
                                arrival.address)
            return mtp.ACK_STALE
        del data
        message = arrival.take(summary.size)
        if summary.kind == "delta":
            message, summary = self._apply_delta(message, summary)
        elif self._verify is not None:
            self._verify_within_budget(message, summary)
        try:
            stored = self.received.offer(summary, message, via)
        except StoreFull as e:
            raise Rejected("store_full", str(e)) from None
        self.peers.received(via, summary.vehicle_id, summary.version, nbytes, arrival.seconds,
                            arrival.address, kind)
        if not stored:
            return mtp.ACK_STALE
        rate = nbytes / arrival.seconds / 1e6 if arrival.seconds > 0 else float("inf")
        log.info("map of vehicle %d v%d received via %s (%d bytes%s, %.3f s, %.1f MB/s)",
                 summary.vehicle_id, summary.version, via, nbytes,
                 f" as a delta, {summary.size} as a map" if kind == "delta" else "", arrival.seconds, rate)
        try:
            self.arrivals.put_nowait((summary.vehicle_id, summary.version))
        except queue.Full:
            try:
                self.arrivals.get_nowait()
            except queue.Empty:
                pass
            self.arrivals.put_nowait((summary.vehicle_id, summary.version))
        _notify(self._on_map, "on_map", summary)
        if self.config.relay:
            with self._update:
                self._update.notify_all()
        return mtp.ACK_OK

    def _apply_delta(self, data: bytes, summary: MessageSummary) -> tuple[bytes, MessageSummary]:
        """The full map message a delta makes of the map held for its vehicle, and its summary: rebuilt
        from the held map and checked (the CRC of its cells), one at a time like a decode, its memory
        charged to the budget. Rejected("delta_base") when the held map is not the delta's base."""
        from . import delta, wire

        vid = summary.vehicle_id
        held = self.received.get(vid)
        if held is None or held.version != summary.base_version:
            holding = "no map" if held is None else f"v{held.version}"
            raise Rejected("delta_base", f"delta of vehicle {vid} v{summary.base_version} -> "
                                         f"v{summary.version}: holding {holding}")
        s = self.config.transport
        limits = wire.DecodeLimits(max_cells=s.max_cells, max_bytes=s.max_bytes)
        try:
            base_cells = wire.peek(held.data).cells
        except ValueError as e:
            raise Rejected("delta_base", f"the held map of vehicle {vid} does not read: {e}") from None
        need = DECODE_BYTES_PER_CELL * (base_cells + summary.cells)
        with self._decoding:
            if self._budget is not None and not self._budget.add(DECODE_LEDGER, need):
                raise Rejected("memory", f"applying the delta of vehicle {vid} needs {need >> 20} MiB, more "
                                         f"than the memory budget has free")
            try:
                base, base_meta = wire.decode_map(held.data, limits)
                grid, meta = delta.apply_delta(base, base_meta, data, limits)
                message = wire.encode_map(grid, meta, delta.peek_delta(data).map_encoding)
            except delta.DeltaBaseError as e:
                raise Rejected("delta_base", f"delta of vehicle {vid}: {e}") from None
            except (ValueError, MemoryError) as e:
                raise Rejected("decode", f"delta of vehicle {vid}: {e}") from None
            finally:
                if self._budget is not None:
                    self._budget.add(DECODE_LEDGER, -need)
        return message, MessageSummary(vid, summary.version, len(message), grid.size)

    def _verify_within_budget(self, message, summary: MessageSummary) -> None:
        """Decode a received map once (verify), one at a time, its memory charged to the budget."""
        need = DECODE_BYTES_PER_CELL * summary.cells
        with self._decoding:
            if self._budget is not None and not self._budget.add(DECODE_LEDGER, need):
                raise Rejected("memory", f"decoding the map of vehicle {summary.vehicle_id} needs "
                                         f"{need >> 20} MiB, more than the memory budget has free")
            try:
                self._verify(message)
            except (ValueError, MemoryError) as e:
                raise Rejected("decode", f"map from vehicle {summary.vehicle_id}: {e}") from None
            finally:
                if self._budget is not None:
                    self._budget.add(DECODE_LEDGER, -need)

    def _own_refused(self, peer_vid: int, version: int, status: int) -> None:
        if self._on_own_refused is None:
            return
        try:
            self._on_own_refused(peer_vid, version, status)
        except Exception:
            log.exception("on_own_refused callback failed for vehicle %d v%d", peer_vid, version)

    def _accept_result(self, arrival: Arrival, summary: MessageSummary, via: int) -> int:
        """A merge-result message: only from the vehicle that computed it, decoded, kept if newer."""
        from . import wire

        if summary.vehicle_id != via:
            raise Rejected("relayed_result", f"merge result of vehicle {summary.vehicle_id} sent by {via}")
        vid = summary.vehicle_id
        if summary.version > (time.time() + self.config.max_epoch_ahead_s) * 1e6:
            raise Rejected("version", f"merge result of vehicle {vid}: version {summary.version} µs is in "
                                      f"the future")
        if vid == self.vehicle_id or summary.version <= self.results.version(vid):
            self.peers.received(via, summary.vehicle_id, summary.version, summary.size, arrival.seconds,
                                arrival.address, kind="result")
            return mtp.ACK_STALE
        try:
            message = wire.decode_merge_result(arrival.take(summary.size))
        except ValueError as e:
            raise Rejected("decode", f"merge result from vehicle {summary.vehicle_id}: {e}") from None
        try:
            self.results.offer(message)
        except StoreFull as e:
            raise Rejected("store_full", str(e)) from None
        self.peers.received(via, summary.vehicle_id, summary.version, summary.size, arrival.seconds,
                            arrival.address, kind="result")
        log.info("merge result of vehicle %d v%d received (%d edges)", summary.vehicle_id,
                 summary.version, len(message.edges))
        _notify(self._on_result, "on_result", summary)
        return mtp.ACK_OK

    # ------------------------------------------------------------------ discovery
    def set_peers(self, specs, ports=None) -> None:
        """Replace the scanned addresses (e.g. on a config reload)."""
        targets = discovery.parse_targets(specs, self.config.peer_ports if ports is None else ports)
        with self._lock:
            self._targets = targets

    def scan_once(self) -> int:
        """Probe every target without a live sender; start senders for new peers. Returns peers found."""
        now = time.monotonic()
        with self._lock:
            todo = [t for t in self._targets
                    if t not in self._busy_targets and t not in self._self_targets
                    and self._backoff.get(t, (0.0, 0))[0] <= now
                    and not (t in self._alias_targets and self.peers.is_connected(self._alias_targets[t]))]
        found = 0
        source = None if self.config.listen_host in ("", "0.0.0.0", "::") else self.config.listen_host
        for target, sock in discovery.probe(todo, self.config.transport.connect_timeout, source):
            link = PeerLink(sock, self.config.transport, self.vehicle_id, target[0], self._server.instance,
                            deltas=self.config.deltas)
            sender = _Sender(self, link, target)
            with self._lock:
                if self._stop.is_set():
                    sock.close()
                    break
                self._busy_targets.add(target)
                self._all_senders.add(sender)
            sender.thread.start()
            found += 1
        self.scans += 1
        for vid in self.peers.forget_stale(self.config.grace_period):
            log.info("peer vehicle %d dropped: not seen for %.0f s", vid, self.config.grace_period)
        return found

    def _scan_loop(self) -> None:
        while not self._stop.is_set():
            try:
                self.scan_once()
            except Exception:  # a scan must never kill discovery
                log.exception("discovery scan failed")
            self._stop.wait(self.config.scan_period)

    def _register(self, vid: int, sender: "_Sender") -> bool:
        with self._lock:
            self._unnamed_at.pop(sender.target, None)
            live = self._senders.get(vid)
            if live is not None and live.thread.is_alive() and live is not sender:
                return False
            self._senders[vid] = sender
            return True

    def _unregister(self, sender: "_Sender", handshake_failed: bool) -> None:
        with self._lock:
            self._all_senders.discard(sender)
            self._busy_targets.discard(sender.target)
            if handshake_failed:  # e.g. wrong swarm key or block size: retry later, not every scan
                self._unnamed_at[sender.target] = time.monotonic()
                _, n = self._backoff.get(sender.target, (0.0, 0))
                delay = min(60.0, self.config.scan_period * 2 ** min(n, 10))
                self._backoff[sender.target] = (time.monotonic() + delay, n + 1)
            else:
                self._backoff.pop(sender.target, None)
            if sender.vid is not None and self._senders.get(sender.vid) is sender:
                del self._senders[sender.vid]

    def _forgive(self, host: str) -> None:
        """A hello'd peer at host just got a transfer through (with the key, if one is set): whatever
        failed our handshakes with it (a wrong key, since fixed) is over, so scan it again at once."""
        with self._lock:
            for target in [t for t in self._backoff if t[0] == host]:
                del self._backoff[target]

    def _mark_self(self, target) -> None:
        with self._lock:
            self._self_targets.add(target)
            self._unnamed_at.pop(target, None)

    def _mark_alias(self, target, vid: int) -> None:
        with self._lock:
            self._alias_targets[target] = vid
            self._unnamed_at.pop(target, None)

    def stats(self) -> dict:
        """Everything coopctl status shows about sharing."""
        own = self._own
        snap = self.peers.snapshot()
        snap.update({
            "vehicle_id": self.vehicle_id,
            "listen": None if self.address is None else host_port(*self.address),
            "published_version": None if own is None else own[0],
            "published_result_version": None if self._own_result is None else self._own_result[0],
            "received_maps": {m.vehicle_id: m.version for m in self.received.all()},
            "received_results": {r.vehicle_id: r.version for r in self.results.all()},
            "received_bytes_held": self.received.total_bytes(),
            "evicted_maps": self.received.evicted,
            "open_connections": self._server.open_connections,
            "inflight_bytes": self._server.inflight_bytes,
            "receiving": self._server.receiving(),
            "connections_accepted": self._server.accepted,
            "refused_busy": self._server.refused_busy, "evicted_idle": self._server.evicted_idle,
            "scans": self.scans,
            "transports": ["mtp"] * self.config.mtp + ["zenoh"] * (self.zenoh is not None),
        })
        if self.zenoh is not None:
            snap["zenoh"] = self.zenoh.stats()
        return snap


class _Sender:
    """One thread per discovered peer: hello, then send whatever the peer lacks, on every update."""

    def __init__(self, service: SharingService, link: PeerLink, target):
        self.service, self.link, self.target = service, link, target
        self.vid: int | None = None
        self.deltas = False
        """The peer reads map deltas (its hello says so, and it has not refused one)."""
        self._wire_counted = 0
        self.thread = threading.Thread(target=self.run, name=f"coopd-share-send-{target[0]}", daemon=True)

    def run(self) -> None:
        svc = self.service
        try:
            self._run()
        except (OSError, ValueError) as e:  # MtpError is a ValueError; TimeoutError an OSError
            cause = getattr(e, "cause", "timeout" if isinstance(e, TimeoutError) else "cut")
            if not svc._stop.is_set():
                svc.peers.failure(cause, self.vid, self.target[0])
                where = host_port(*self.target)
                if self.link.peer is None and svc._backoff.get(self.target, (0, 0))[1] > 0:
                    log.debug("handshake with %s failed again: %s: %s", where, cause, e)
                else:
                    log.warning("sending to %s (vehicle %s) failed: %s: %s", where, self.vid, cause, e)
        finally:
            self.link.close()
            if self.vid is not None:
                svc.peers.disconnected(self.vid)
            svc._unregister(self, handshake_failed=self.link.peer is None)

    def _run(self) -> None:
        svc = self.service
        hello = self.link.handshake()
        if hello.vehicle_id == svc.vehicle_id:
            svc._mark_self(self.target)
            return
        self.vid = hello.vehicle_id
        if not svc._register(self.vid, self):
            svc._mark_alias(self.target, self.vid)  # the vehicle is already served at another address
            self.vid = None
            return
        if svc.peers.hello(self.vid, hello.instance):
            svc._delta_refused_by.discard(self.vid)
        svc.peers.seen(self.vid, *self.target, connected=True)
        self.deltas = hello.deltas and svc.config.deltas and self.vid not in svc._delta_refused_by
        log.info("peer vehicle %d found at %s", self.vid, host_port(*self.target))
        while not svc._stop.is_set():
            for origin, version, message, kind in svc.pending_for(self.vid):
                if svc._stop.is_set():
                    return
                if origin != svc.vehicle_id and self.link.offer(origin, version) == mtp.ACK_STALE:
                    svc.peers.peer_has(self.vid, origin, version)  # relay declined: it has it already
                    svc.peers.offer_declined(self.vid)
                    continue
                message, kind, status, seconds = self._send(origin, version, message, kind)
                if status == mtp.ACK_OK:
                    svc.peers.sent(self.vid, origin, version, len(message), seconds, kind)
                    log.info("%s of vehicle %d v%d sent to vehicle %d (%d bytes, %.3f s)",
                             {"result": "merge result", "delta": "map delta"}.get(kind, "map"),
                             origin, version, self.vid, len(message), seconds)
                else:
                    svc.peers.peer_has(self.vid, origin, version, redundant=status == mtp.ACK_STALE,
                                       kind=kind)
                    if status != mtp.ACK_STALE:
                        svc.peers.failure("version_refused" if status == mtp.ACK_VERSION else
                                          "rejected_by_peer", self.vid)
                    own_map = origin == svc.vehicle_id and kind in ("map", "delta")
                    if own_map and status in (mtp.ACK_STALE, mtp.ACK_VERSION) \
                            and not self._relayed_copy(version, status):
                        svc._own_refused(self.vid, version, status)
            svc.peers.wire_sent(self.vid, self.link.wire_bytes_sent - self._wire_counted)
            self._wire_counted = self.link.wire_bytes_sent
            with svc._update:
                if not svc.pending_for(self.vid) and not svc._stop.is_set():
                    svc._update.wait(SENDER_IDLE_S)
            if self.link.closed_by_peer():
                log.info("peer vehicle %d closed the connection", self.vid)
                return
            svc.peers.seen(self.vid)

    def _relayed_copy(self, version: int, status: int) -> bool:
        """Whether a peer that answered ACK_STALE to our own map holds exactly that version: our map
        relayed to it by another peer first, not a newer one we never sent (which pins our versions and
        needs a new epoch). An offer of the next version tells them apart: OK means it holds no newer."""
        return status == mtp.ACK_STALE and self.link.offer(self.service.vehicle_id, version + 1) == mtp.ACK_OK

    def _send(self, origin: int, version: int, message: bytes, kind: str) -> tuple[bytes, str, int, float]:
        """Send one pending message; our own map as a delta when the peer reads them and the ledger has
        one from the version it holds, and in full at once if the peer refuses the delta. Returns (what
        was sent last, its kind, ack status, seconds)."""
        svc = self.service
        if kind == "map" and origin == svc.vehicle_id and self.deltas:
            data = svc.own_delta(self.vid, version)
            if data is not None:
                status, seconds = self.link.send_map(data)
                if status not in (mtp.ACK_DELTA_BASE, mtp.ACK_REJECTED):
                    return data, "delta", status, seconds
                svc.peers.delta_fallback(self.vid)
                if status == mtp.ACK_REJECTED:  # it cannot read them after all: full maps until it restarts
                    self.deltas = False
                    svc._delta_refused_by.add(self.vid)
                log.info("vehicle %d %s our map delta v%d: sending the full map", self.vid,
                         "refused" if status == mtp.ACK_REJECTED else "does not hold the base of", version)
        status, seconds = self.link.send_map(message)
        return message, kind, status, seconds

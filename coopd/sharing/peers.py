"""Who we share with: the peer table (keyed by vehicle id), per-peer stats and version tracking,
the received-map store (newest version per vehicle, kept as serialized bytes) and the received
merge-result store (newest result message per sender, decoded)."""

import logging
import threading
import time
from collections import Counter
from dataclasses import dataclass, field

log = logging.getLogger("coopd.sharing")

VEHICLE_IDS = range(1, 256)
"""Vehicle ids a swarm member can have (vehicle.id, the MAVLink system id): anything else in a
hello or a received message is refused."""


@dataclass(frozen=True)
class MessageSummary:
    """What the transport needs to know about a serialized map message, read from its header."""

    vehicle_id: int
    version: int
    size: int
    """Bytes of the whole message (where it ends inside the zero-padded data blocks)."""
    cells: int
    kind: str = "map"
    """"map" (types 0/1), "delta" (type 4: a map as the changes since base_version) or "result" (type 2,
    merge results): versions are tracked per kind, a delta's as a map's."""
    base_version: int = 0
    """A delta's: the version of the map it applies to."""


@dataclass
class PeerStats:
    """Everything coopctl status shows about one peer."""

    vehicle_id: int | None
    address: str = ""
    port: int = 0
    last_seen: float = 0.0
    connected: bool = False
    maps_sent: int = 0
    bytes_sent: int = 0
    offers_declined: int = 0
    """Relay offers the peer declined because it already held the map (no transfer made)."""
    redundant_sent: int = 0
    """Transfers the peer answered 'stale' (it already held that version, e.g. from a relay)."""
    maps_received: int = 0
    bytes_received: int = 0
    last_transfer_s: float = 0.0
    last_throughput_bps: float = 0.0
    failures: Counter = field(default_factory=Counter)
    instance: int = 0
    """The peer daemon's instance id from its hello; a new one resets `has`."""
    has: dict = field(default_factory=dict)
    """origin vehicle id -> newest map version this peer is known to hold (sent or received)."""
    has_results: dict = field(default_factory=dict)
    """origin vehicle id -> newest merge-result version this peer is known to hold."""
    results_sent: int = 0
    results_received: int = 0
    deltas_sent: int = 0
    """Maps sent as deltas (counted in maps_sent too)."""
    deltas_received: int = 0
    delta_fallbacks: int = 0
    """Deltas the peer refused because it did not hold their base: the full map was sent instead."""
    wire_bytes_sent: int = 0
    """Every MTP frame and data block we sent the peer (hello, proof, offers, transfers)."""

    def snapshot(self, now: float) -> dict:
        return {
            "vehicle_id": self.vehicle_id, "address": self.address, "port": self.port,
            "last_seen_ago_s": round(now - self.last_seen, 3), "connected": self.connected,
            "maps_sent": self.maps_sent, "bytes_sent": self.bytes_sent,
            "redundant_sent": self.redundant_sent, "offers_declined": self.offers_declined,
            "maps_received": self.maps_received, "bytes_received": self.bytes_received,
            "last_transfer_s": round(self.last_transfer_s, 6),
            "last_throughput_mbit_s": round(self.last_throughput_bps * 8 / 1e6, 3),
            "failures": dict(self.failures), "has_versions": dict(self.has),
            "results_sent": self.results_sent, "results_received": self.results_received,
            "has_result_versions": dict(self.has_results),
            "deltas_sent": self.deltas_sent, "deltas_received": self.deltas_received,
            "delta_fallbacks": self.delta_fallbacks, "wire_bytes_sent": self.wire_bytes_sent,
        }


class PeerTable:
    """Thread-safe peer stats by vehicle id; failures before a peer is identified go by address."""

    def __init__(self, clock=time.monotonic):
        self._lock = threading.Lock()
        self._peers: dict[int, PeerStats] = {}
        self._anonymous: dict[str, Counter] = {}
        self._clock = clock

    def _get(self, vehicle_id: int) -> PeerStats:
        peer = self._peers.get(vehicle_id)
        if peer is None:
            peer = self._peers[vehicle_id] = PeerStats(vehicle_id)
        return peer

    def seen(self, vehicle_id: int, address: str = "", port: int = 0, connected: bool | None = None) -> None:
        """The peer showed a sign of life (hello, transfer) from `address`."""
        with self._lock:
            peer = self._get(vehicle_id)
            peer.last_seen = self._clock()
            if address:
                peer.address = address
            if port:
                peer.port = port
            if connected is not None:
                peer.connected = connected

    def hello(self, vehicle_id: int, instance: int) -> bool:
        """Record the peer's instance id; True (and `has` forgotten) if it restarted since we last met."""
        with self._lock:
            peer = self._get(vehicle_id)
            restarted = peer.instance != instance
            if restarted:
                peer.instance = instance
                peer.has.clear()
                peer.has_results.clear()
            return restarted

    def disconnected(self, vehicle_id: int) -> None:
        with self._lock:
            if vehicle_id in self._peers:
                self._peers[vehicle_id].connected = False

    def is_connected(self, vehicle_id: int) -> bool:
        with self._lock:
            peer = self._peers.get(vehicle_id)
            return peer is not None and peer.connected

    def sent(self, vehicle_id: int, origin: int, version: int, nbytes: int, seconds: float,
             kind: str = "map") -> None:
        """A message (map, delta or merge result) of `origin` at `version` was delivered and acknowledged."""
        with self._lock:
            peer = self._get(vehicle_id)
            if kind == "result":
                peer.results_sent += 1
            else:
                peer.maps_sent += 1
                peer.deltas_sent += kind == "delta"
            peer.bytes_sent += nbytes
            peer.last_transfer_s = seconds
            peer.last_throughput_bps = nbytes / seconds if seconds > 0 else 0.0
            peer.last_seen = self._clock()
            self._note_has(peer, origin, version, kind)

    def received(self, vehicle_id: int, origin: int, version: int, nbytes: int, seconds: float,
                 address: str = "", kind: str = "map") -> None:
        """A message of `origin` arrived from the peer: it holds at least that version."""
        with self._lock:
            peer = self._get(vehicle_id)
            if kind == "result":
                peer.results_received += 1
            else:
                peer.maps_received += 1
                peer.deltas_received += kind == "delta"
            peer.bytes_received += nbytes
            peer.last_transfer_s = seconds
            peer.last_throughput_bps = nbytes / seconds if seconds > 0 else 0.0
            peer.last_seen = self._clock()
            if address and not peer.address:  # the server address found by discovery wins
                peer.address = address
            self._note_has(peer, origin, version, kind)

    def peer_has(self, vehicle_id: int, origin: int, version: int, redundant: bool = False,
                 kind: str = "map") -> None:
        """Record that the peer holds `origin` at `version` (e.g. it answered 'stale')."""
        with self._lock:
            peer = self._get(vehicle_id)
            peer.redundant_sent += int(redundant)
            self._note_has(peer, origin, version, kind)

    def delta_fallback(self, vehicle_id: int) -> None:
        with self._lock:
            self._get(vehicle_id).delta_fallbacks += 1

    def wire_sent(self, vehicle_id: int, nbytes: int) -> None:
        """Count bytes of frames and data blocks sent to the peer."""
        with self._lock:
            self._get(vehicle_id).wire_bytes_sent += nbytes

    def offer_declined(self, vehicle_id: int) -> None:
        with self._lock:
            self._get(vehicle_id).offers_declined += 1

    @staticmethod
    def _note_has(peer: PeerStats, origin: int, version: int, kind: str = "map") -> None:
        has = peer.has_results if kind == "result" else peer.has
        if version > has.get(origin, -1):
            has[origin] = version

    def has_version(self, vehicle_id: int, origin: int, kind: str = "map") -> int:
        """Newest version of `origin`'s map (or merge result) the peer is known to hold; -1 if none."""
        with self._lock:
            peer = self._peers.get(vehicle_id)
            if peer is None:
                return -1
            return (peer.has_results if kind == "result" else peer.has).get(origin, -1)

    def failure(self, cause: str, vehicle_id: int | None = None, address: str = "") -> None:
        """Count a dropped transfer or connection by cause."""
        with self._lock:
            if vehicle_id is not None:
                self._get(vehicle_id).failures[cause] += 1
            else:
                if address not in self._anonymous and len(self._anonymous) >= 256:
                    address = "other"  # bounded: a scan of hostile addresses cannot grow the table
                self._anonymous.setdefault(address, Counter())[cause] += 1

    def forget_stale(self, grace_s: float) -> list[int]:
        """Drop peers not connected and not seen for `grace_s`; return their vehicle ids."""
        now = self._clock()
        with self._lock:
            gone = [v for v, p in self._peers.items() if not p.connected and now - p.last_seen > grace_s]
            for v in gone:
                del self._peers[v]
            return gone

    def alive(self, within_s: float) -> list[int]:
        """Peers connected or seen within the last within_s seconds."""
        now = self._clock()
        with self._lock:
            return [v for v, p in self._peers.items() if p.connected or now - p.last_seen <= within_s]

    def vehicle_ids(self) -> list[int]:
        with self._lock:
            return list(self._peers)

    def snapshot(self) -> dict:
        """Plain data for coopctl status."""
        with self._lock:
            return {
                "peers": [p.snapshot(self._clock()) for p in self._peers.values()],
                "unidentified_failures": {a: dict(c) for a, c in self._anonymous.items()},
            }


class StoreFull(Exception):
    """Storing a received map would pass the store's bounds."""


@dataclass(frozen=True)
class StoredMap:
    """A received map at rest: serialized (compressed) bytes and what its header says."""

    vehicle_id: int
    version: int
    data: bytes | bytearray
    received_at: float
    via: int | None
    """Vehicle id of the peer that delivered it (differs from vehicle_id for relayed maps)."""


class ReceivedStore:
    """Newest received map per vehicle; a newer version replaces, an older or equal one is refused.

    Version 0 means 'unversioned' (thesis type-0 messages carry no version): it always replaces.
    When holding a new map would pass max_vehicles or max_bytes, the maps received longest ago
    (vehicles not heard from since) are evicted to make room, so vehicles that left, or ids a
    hostile host made up, cannot keep a new drone out.
    """

    def __init__(self, max_vehicles: int = 256, max_bytes: int = 1 << 30):
        self._lock = threading.Lock()
        self._maps: dict[int, StoredMap] = {}
        self._bytes = 0
        self.max_vehicles = max_vehicles
        self.max_bytes = max_bytes
        self.evicted = 0
        self.changed = threading.Condition(self._lock)

    def offer(self, summary: MessageSummary, data: bytes | bytearray, via: int | None = None) -> bool:
        """Store the message if it is newer than what we hold for its vehicle; True if stored.
        Evicts the stalest other maps if needed to stay within max_vehicles and max_bytes; StoreFull
        (nothing changed) only if the map alone is larger than max_bytes."""
        vid = summary.vehicle_id
        with self._lock:
            held = self._maps.get(vid)
            if held is not None and summary.version != 0 and summary.version <= held.version:
                return False
            if len(data) > self.max_bytes:
                raise StoreFull(f"a map of {len(data)} bytes is more than max_received_bytes "
                                f"{self.max_bytes}")
            stalest = sorted((m for v, m in self._maps.items() if v != vid), key=lambda m: m.received_at)
            count = len(self._maps) + (held is None)
            total = self._bytes - (len(held.data) if held else 0) + len(data)
            victims = []
            while count > self.max_vehicles or total > self.max_bytes:
                if len(victims) == len(stalest):
                    raise StoreFull(f"max_vehicles {self.max_vehicles} holds no map")
                victim = stalest[len(victims)]
                victims.append(victim)
                count -= 1
                total -= len(victim.data)
            now = time.time()
            for victim in victims:
                del self._maps[victim.vehicle_id]
                self.evicted += 1
                log.info("received map of vehicle %d v%d evicted (received %.0f s ago) to hold vehicle %d's: "
                         "%d vehicles, %d bytes at most", victim.vehicle_id, victim.version,
                         now - victim.received_at, vid, self.max_vehicles, self.max_bytes)
            self._bytes = total
            self._maps[vid] = StoredMap(vid, summary.version, data, now, via)
            self.changed.notify_all()
            return True

    def version(self, vehicle_id: int) -> int:
        with self._lock:
            held = self._maps.get(vehicle_id)
            return -1 if held is None else held.version

    def get(self, vehicle_id: int) -> StoredMap | None:
        with self._lock:
            return self._maps.get(vehicle_id)

    def all(self) -> list[StoredMap]:
        with self._lock:
            return list(self._maps.values())

    def total_bytes(self) -> int:
        with self._lock:
            return self._bytes


class ResultStore:
    """Newest merge-result message per sender (decoded, each at most wire.MAX_EDGES edges), at most
    max_vehicles senders: a few kilobytes each, so bounded without a byte budget."""

    def __init__(self, max_vehicles: int = 256):
        self._lock = threading.Lock()
        self._results: dict = {}
        self.max_vehicles = max_vehicles

    def offer(self, message) -> bool:
        """Store a wire.MergeResultMessage if newer than the sender's held one; StoreFull if the
        store holds max_vehicles senders already."""
        with self._lock:
            held = self._results.get(message.vehicle_id)
            if held is not None and message.version <= held.version:
                return False
            if held is None and len(self._results) >= self.max_vehicles:
                raise StoreFull(f"already holding merge results of {len(self._results)} vehicles")
            self._results[message.vehicle_id] = message
            return True

    def version(self, vehicle_id: int) -> int:
        with self._lock:
            held = self._results.get(vehicle_id)
            return -1 if held is None else held.version

    def all(self) -> list:
        with self._lock:
            return list(self._results.values())

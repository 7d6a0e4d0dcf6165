"""Zenoh as a second transport for the same messages MTP carries (docs/sharing.md, "Zenoh").

Every vehicle publishes its latest map and merge result under

    coopd/<swarm>/<vehicle id>/map       coopd/<swarm>/<vehicle id>/merge

and answers queries for them (a queryable), so a drone that joins late fetches each at once: it
watches the liveliness tokens coopd/<swarm>/<vehicle id>/alive and queries every vehicle it sees
appear. Discovery and multi-hop routing are Zenoh's (scouting, gossip, configured endpoints or a
zenohd router). What arrives goes through the sharing service's receive path exactly as an MTP
transfer does (header checks, allowed vehicles, cell cap, newer versions only, decode within the
memory budget); this module only adds the envelope:

    b"CZ" + flags (1 byte) [+ nonce (12 bytes)] + payload

flags 0: the payload is the message itself (sharing.open, no swarm key); flags 1: the payload is
the message sealed with ChaCha20-Poly1305 under HKDF-SHA256(swarm key, info = ENVELOPE_INFO), a
random nonce, and the key expression as associated data, so a message is authenticated per
message, unreadable without the key, and cannot be moved to another vehicle's key expression. A
replayed old message carries an old version and is refused as such.
"""

from __future__ import annotations

import logging
import os
import queue
import re
import struct
import threading
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field

from .peers import VEHICLE_IDS
from .transport import Arrival, DropLog, Rejected
from .zenoh_tls import check_tls, describe_tls, tls_config

log = logging.getLogger("coopd.sharing")

MAGIC = b"CZ"
OPEN, SEALED = 0, 1
HEAD = struct.Struct("<2sB")
NONCE_SIZE = 12
TAG_SIZE = 16
ENVELOPE_INFO = b"coopd-zenoh/1 envelope"
KINDS = {"map": "map", "merge": "result", "delta": "delta"}
"""Key expression suffix -> the wire message kind it must carry."""
QUEUE_MESSAGES = 8
"""Received publications waiting for the receive thread; more are dropped (counted)."""
MAX_ALIVE = 1024
"""Vehicles' liveliness tokens remembered at most (anyone on the network can declare one)."""
QUERY_TIMEOUT_S = 5.0
INBOX_LEDGER = "sharing-zenoh-inbox"
"""The memory budget's entry for received publications waiting for the receive thread."""
ENDPOINT = re.compile(r"^(tcp|udp|tls|quic|ws|unixsock-stream)/\S+$")
MODES = ("peer", "router", "client")
SWARM_NAME = re.compile(r"^[A-Za-z0-9_-]{1,64}$")


def _doc(text: str, default):
    return field(default=default, metadata={"doc": text})


@dataclass(frozen=True)
class ZenohSettings:
    """[sharing.zenoh]: how this vehicle joins the Zenoh network (with transport "zenoh" or "both")."""

    swarm: str = _doc("key expressions are coopd/<swarm>/...: swarms on one Zenoh network stay apart",
                      "swarm")
    mode: str = _doc("'peer': talk to the drones in reach; 'router': also route for the others, so maps "
                     "cross drones that cannot reach each other; 'client': through a zenohd router", "peer")
    listen: tuple[str, ...] = _doc("endpoints to listen on, e.g. 'tcp/0.0.0.0:7447'; empty: Zenoh's "
                                   "default for the mode", ())
    connect: tuple[str, ...] = _doc("endpoints (peers or routers) to connect to, e.g. 'tcp/10.42.0.1:7447'",
                                    ())
    multicast_scouting: bool = _doc("find peers by UDP multicast scouting (off: connect endpoints and "
                                    "gossip only)", True)
    tls_root_ca: str = _doc("PEM file of the swarm CA's certificate: peers' certificates must be signed by "
                            "it (needed with tls/ or quic/ endpoints; empty: no TLS)", "")
    tls_certificate: str = _doc("PEM file of this drone's certificate, signed by the swarm CA, presented on "
                                "every TLS link", "")
    tls_private_key: str = _doc("PEM file of that certificate's private key (unencrypted; readable by coopd "
                                "only)", "")
    tls_client_auth: bool = _doc("mutual TLS: a peer connecting to us must present a certificate the swarm "
                                 "CA signed, and we present ours when connecting", True)
    tls_verify_name: bool = _doc("when connecting, the peer's certificate must name the address connected "
                                 "to (subjectAltName); false: any certificate the swarm CA signed", True)

    def __post_init__(self):
        if not SWARM_NAME.match(self.swarm):
            raise ValueError(f"swarm name {self.swarm!r}: 1..64 letters, digits, '-' or '_'")
        if self.mode not in MODES:
            raise ValueError(f"mode {self.mode!r} is one of {', '.join(MODES)}")
        for e in (*self.listen, *self.connect):
            if not ENDPOINT.match(e):
                raise ValueError(f"endpoint {e!r} is not PROTOCOL/ADDRESS (tcp/10.0.0.1:7447, "
                                 "quic/..., tls/...)")
        check_tls(self)


def key_expr(swarm: str, vehicle_id: int, kind: str) -> str:
    return f"coopd/{swarm}/{vehicle_id}/{kind}"


def parse_key(swarm: str, key: str, kinds=KINDS) -> tuple[int, str] | None:
    """(vehicle id, kind) of a key expression of this swarm, or None: `kinds` maps the last chunk to
    the kind returned (by default the wire kinds published; {"alive": "alive"} for liveliness)."""
    parts = key.split("/")
    if len(parts) != 4 or parts[0] != "coopd" or parts[1] != swarm or parts[3] not in kinds:
        return None
    if not parts[2].isdigit() or len(parts[2]) > 3 or int(parts[2]) not in VEHICLE_IDS:
        return None
    return int(parts[2]), kinds[parts[3]]


def envelope_cipher(swarm_key: bytes):
    """The AEAD every keyed vehicle seals its Zenoh publications with."""
    from cryptography.hazmat.primitives import hashes
    from cryptography.hazmat.primitives.ciphers.aead import ChaCha20Poly1305
    from cryptography.hazmat.primitives.kdf.hkdf import HKDF

    derived = HKDF(algorithm=hashes.SHA256(), length=32, salt=None, info=ENVELOPE_INFO).derive(swarm_key)
    return ChaCha20Poly1305(derived)


def seal(cipher, key: str, message) -> bytes:
    """The envelope of one message published under `key` (cipher None: open)."""
    if cipher is None:
        return HEAD.pack(MAGIC, OPEN) + bytes(message)
    nonce = os.urandom(NONCE_SIZE)
    return HEAD.pack(MAGIC, SEALED) + nonce + cipher.encrypt(nonce, bytes(message), key.encode())


def unseal(cipher, key: str, payload) -> bytes:
    """The message in an envelope received under `key`; Rejected ("malformed" or "auth") when it is not
    one this vehicle accepts (no envelope, sealed without our key, open while we have a key, tampered,
    moved to another key expression)."""
    from cryptography.exceptions import InvalidTag

    view = memoryview(payload)
    if len(view) < HEAD.size:
        raise Rejected("malformed", f"{len(view)} bytes: shorter than the envelope header")
    magic, flags = HEAD.unpack_from(view)
    if magic != MAGIC or flags not in (OPEN, SEALED):
        raise Rejected("malformed", "not a coopd envelope")
    if cipher is None:
        if flags != OPEN:
            raise Rejected("auth", "sealed with a swarm key, and this vehicle has none")
        return bytes(view[HEAD.size:])
    if flags != SEALED:
        raise Rejected("auth", "not sealed, and this vehicle requires the swarm key")
    if len(view) < HEAD.size + NONCE_SIZE + TAG_SIZE:
        raise Rejected("malformed", "sealed envelope shorter than its nonce and tag")
    nonce = bytes(view[HEAD.size:HEAD.size + NONCE_SIZE])
    try:
        return cipher.decrypt(nonce, view[HEAD.size + NONCE_SIZE:], key.encode())
    except InvalidTag:
        raise Rejected("auth", "does not authenticate under the swarm key for this key expression") from None


def zenoh_config(settings: ZenohSettings, max_message_bytes: int):
    """A zenoh.Config from our settings (imported here: Zenoh is an optional extra); a message larger
    than max_message_bytes is not reassembled by Zenoh at all."""
    import json

    import zenoh

    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps(settings.mode))
    if settings.listen:
        conf.insert_json5("listen/endpoints", json.dumps(list(settings.listen)))
    if settings.connect:
        conf.insert_json5("connect/endpoints", json.dumps(list(settings.connect)))
    conf.insert_json5("scouting/multicast/enabled", json.dumps(settings.multicast_scouting))
    conf.insert_json5("transport/link/rx/max_message_size", str(max_message_bytes))
    # Shared memory only serves Zenoh sessions on this host (other vehicles are other hosts), and would
    # reserve a pool (16 MiB by default) the memory budget does not see; off, a session on loopback
    # (tests, benchmarks, a simulated swarm) carries maps over TCP as the network does.
    conf.insert_json5("transport/shared_memory/enabled", "false")
    tls = tls_config(settings)
    if tls is not None:
        conf.insert_json5("transport/link/tls", json.dumps(tls))
    return conf


class ZenohLink:
    """One vehicle on the Zenoh network: publishes our latest messages, serves them to queries, and
    hands what it receives to accept (the sharing service's receive path) on its own thread.

    inspect(message) -> MessageSummary reads a message's header; accept(Arrival) -> ack status, raising
    Rejected(cause, detail) for a refused message; failure(cause, vehicle id, address) counts a drop
    where MTP's drops are counted; ledger (optional MemoryBudget) is charged with the queued
    messages' bytes."""

    def __init__(self, settings: ZenohSettings, vehicle_id: int, swarm_key: bytes | None,
                 inspect: Callable, accept: Callable[[Arrival], int],
                 failure: Callable[[str, int | None, str], None], max_message_bytes: int, ledger=None):
        self.settings, self.vehicle_id = settings, vehicle_id
        self._inspect = inspect
        self.max_message_bytes = max_message_bytes + HEAD.size + NONCE_SIZE + TAG_SIZE
        self._cipher = None if swarm_key is None else envelope_cipher(swarm_key)
        self._accept, self._failure, self._ledger = accept, failure, ledger
        self._latest: dict[str, bytes] = {}  # kind -> our newest sealed envelope (served to queries)
        self._unsent: dict[str, bytes] = {}  # kind -> newest envelope the send thread has not put yet
        self._new = threading.Condition()
        self._inbox: queue.Queue = queue.Queue(QUEUE_MESSAGES)
        self._fetch: queue.Queue = queue.Queue(256)
        self._wanted: set[str] = set()  # vehicles waiting in _fetch (each once)
        self._wanted_lock = threading.Lock()
        self._alive: set[int] = set()  # vehicles whose liveliness token is up (not authenticated)
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self.counters: Counter = Counter()
        self.drops = DropLog()
        self.session = None
        self._entities: list = []

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> ZenohLink:
        """Open the session and declare everything; OSError when Zenoh is missing or cannot open."""
        try:
            import zenoh
        except ImportError as e:
            raise OSError(f"zenoh: the eclipse-zenoh package is missing ({e}); pip install 'coopd[zenoh]' "
                          "or set sharing.transport = \"mtp\"") from e
        s = self.settings
        try:
            self.session = zenoh.open(zenoh_config(s, self.max_message_bytes))
        except zenoh.ZError as e:
            raise OSError(f"zenoh: cannot open the session ({e})") from e
        base = f"coopd/{s.swarm}"
        self._entities = [
            self.session.declare_subscriber(f"{base}/*/map", self._on_sample),
            self.session.declare_subscriber(f"{base}/*/merge", self._on_sample),
            self.session.declare_subscriber(f"{base}/*/delta", self._on_sample),
            self.session.declare_queryable(f"{base}/{self.vehicle_id}/*", self._on_query),
            self.session.liveliness().declare_token(f"{base}/{self.vehicle_id}/alive"),
            self.session.liveliness().declare_subscriber(f"{base}/*/alive", self._on_alive, history=True),
        ]
        for target, name in ((self._receive_loop, "coopd-zenoh-rx"), (self._fetch_loop, "coopd-zenoh-fetch"),
                             (self._send_loop, "coopd-zenoh-tx")):
            t = threading.Thread(target=target, name=name, daemon=True)
            t.start()
            self._threads.append(t)
        log.info("zenoh: %s %s as vehicle %d (listen %s, connect %s, multicast scouting %s, %s, %s)",
                 s.mode, self.session.zid(), self.vehicle_id, ", ".join(s.listen) or "default",
                 ", ".join(s.connect) or "none", "on" if s.multicast_scouting else "off", describe_tls(s),
                 "sealed with the swarm key" if self._cipher else "OPEN: no swarm key")
        return self

    def stop(self) -> None:
        self._stop.set()
        with self._new:
            self._new.notify_all()
        for q in (self._inbox, self._fetch):
            try:
                q.put_nowait(None)
            except queue.Full:
                pass
        for t in self._threads:
            t.join(5)
        if self.session is not None:
            self.session.close()
            self.session = None

    # ------------------------------------------------------------------ publishing
    def publish(self, kind: str, message: bytes) -> None:
        """Offer our newest message of a kind ('map' or 'merge'): kept for queries at once, put on the
        network by the send thread (a newer one replaces one not yet sent)."""
        envelope = self._seal(kind, message)
        with self._new:
            self._latest[kind] = envelope
            self._unsent[kind] = envelope
            self._new.notify_all()

    def publish_map(self, message: bytes, delta: bytes | None = None) -> None:
        """Offer our newest map: the full message is what queries get; on the network goes the delta
        from the map published before it when there is one (a vehicle that holds that map applies it,
        any other fetches the full map), else the full map. A delta still unsent when the next map
        comes would skip a version, so the full map goes instead."""
        full = self._seal("map", message)
        with self._new:
            self._latest["map"] = full
            if delta is not None and "delta" not in self._unsent and "map" not in self._unsent:
                self._unsent["delta"] = self._seal("delta", delta)
            else:
                self._unsent.pop("delta", None)
                self._unsent["map"] = full
            self._new.notify_all()

    def _seal(self, kind: str, message: bytes) -> bytes:
        return seal(self._cipher, key_expr(self.settings.swarm, self.vehicle_id, kind), message)

    def _send_loop(self) -> None:
        """Put each newest message reliably (congestion control BLOCK: on a slow link it waits for room
        instead of dropping the update), on this thread, so no other thread waits for the network."""
        import zenoh

        while not self._stop.is_set():
            with self._new:
                while not self._unsent and not self._stop.is_set():
                    self._new.wait()
                unsent, self._unsent = self._unsent, {}
            for kind, envelope in unsent.items():
                if self._stop.is_set() or self.session is None:
                    return
                try:
                    self.session.put(key_expr(self.settings.swarm, self.vehicle_id, kind), envelope,
                                     congestion_control=zenoh.CongestionControl.BLOCK)
                except Exception as e:  # the session closing under us
                    self.counters["publish_failed"] += 1
                    log.debug("zenoh: publishing our %s failed: %s", kind, e)
                    continue
                self.counters["published" if kind != "delta" else "published_delta"] += 1
                self.counters["bytes_out"] += len(envelope)

    def _on_query(self, query) -> None:
        """Answer a query for our latest map / merge (Zenoh's thread: no work beyond the reply)."""
        base = f"coopd/{self.settings.swarm}/{self.vehicle_id}/"
        with self._new:
            latest = dict(self._latest)
        for kind, envelope in latest.items():
            try:
                query.reply(base + kind, envelope)
                self.counters["queries_answered"] += 1
                self.counters["bytes_out"] += len(envelope)
            except Exception as e:  # the querier left: nothing to do
                self.counters["query_reply_failed"] += 1
                log.debug("zenoh: reply to %s failed: %s", query.selector, e)

    # ------------------------------------------------------------------ receiving
    def _on_sample(self, sample) -> None:
        """A publication (Zenoh's thread): queue it for the receive thread, or count the drop."""
        self._enqueue(str(sample.key_expr), sample.payload.to_bytes())

    def _on_alive(self, sample) -> None:
        """A vehicle's liveliness token appeared: fetch its latest map and merge result; it went:
        forget it."""
        parsed = parse_key(self.settings.swarm, str(sample.key_expr), {"alive": "alive"})
        if parsed is None or parsed[0] == self.vehicle_id:
            return
        vid = parsed[0]
        if str(sample.kind).endswith("PUT"):
            if len(self._alive) < MAX_ALIVE:
                self._alive.add(vid)
            self._want(str(vid))
        else:
            self._alive.discard(vid)

    def vehicles_alive(self) -> set[int]:
        """Vehicles whose liveliness token is up: their maps are coming if not held yet."""
        return set(self._alive)

    def _want(self, vid: str) -> None:
        """Have the fetch thread query this vehicle's latest map and merge result (once, however
        often it is asked before the query runs)."""
        with self._wanted_lock:
            if vid in self._wanted:
                return
            self._wanted.add(vid)
        try:
            self._fetch.put_nowait(vid)
        except queue.Full:
            with self._wanted_lock:
                self._wanted.discard(vid)
            self.counters["fetch_dropped"] += 1

    def _fetch_loop(self) -> None:
        while not self._stop.is_set():
            vid = self._fetch.get()
            if vid is None or self.session is None:
                return
            with self._wanted_lock:
                self._wanted.discard(vid)
            if not vid.isdigit():
                continue
            try:
                selector = f"coopd/{self.settings.swarm}/{vid}/*"
                for reply in self.session.get(selector, timeout=QUERY_TIMEOUT_S):
                    if reply.ok is not None:  # our own thread: wait for room rather than drop
                        self._enqueue(str(reply.ok.key_expr), reply.ok.payload.to_bytes(), QUERY_TIMEOUT_S)
                        self.counters["fetched"] += 1
            except Exception as e:  # a session closing under us, a peer leaving mid-query
                self.counters["fetch_failed"] += 1
                log.debug("zenoh: fetching vehicle %s failed: %s", vid, e)

    def _enqueue(self, key: str, payload: bytes, wait_s: float = 0.0) -> None:
        """Queue a message for the receive thread, waiting up to wait_s for room (Zenoh's own threads
        never wait). A publication that finds the queue full is dropped (`busy`) and its vehicle
        fetched again by query once there is room: many drones publishing at once (a swarm coming
        up) must not lose a map for good."""
        parsed = parse_key(self.settings.swarm, key)
        if parsed is None or parsed[0] == self.vehicle_id:
            self.counters["ignored"] += parsed is None  # our own publications come back: not counted
            return
        self.counters["bytes_in"] += len(payload)
        if len(payload) > self.max_message_bytes:  # Zenoh's own limit should have stopped it
            self._drop("oversize", parsed[0], key, f"{len(payload)} bytes, limit {self.max_message_bytes}")
            return
        if self._ledger is not None and not self._ledger.add(INBOX_LEDGER, len(payload)):
            self._drop("memory", parsed[0], key, f"{len(payload)} bytes do not fit the memory budget")
            return
        try:
            item = (key, parsed, payload, time.monotonic())
            self._inbox.put(item, block=wait_s > 0, timeout=wait_s or None)
        except queue.Full:
            if self._ledger is not None:
                self._ledger.add(INBOX_LEDGER, -len(payload))
            self._drop("busy", parsed[0], key, f"{QUEUE_MESSAGES} messages already waiting")
            if wait_s == 0:
                self._want(str(parsed[0]))

    def _receive_loop(self) -> None:
        while not self._stop.is_set():
            item = self._inbox.get()
            if item is None:
                return
            key, (vid, kind), payload, queued_at = item
            try:
                self._receive(key, vid, kind, payload, queued_at)
            finally:
                if self._ledger is not None:
                    self._ledger.add(INBOX_LEDGER, -len(payload))

    def _receive(self, key: str, vid: int, kind: str, payload: bytes, queued_at: float) -> None:
        try:
            message = unseal(self._cipher, key, payload)
            try:
                summary = self._inspect(message)
            except ValueError as e:
                raise Rejected("malformed", f"message header: {e}") from None
            if summary.size != len(message):  # no blocks, so no padding: exactly the message
                raise Rejected("size", f"message says {summary.size} bytes, the publication holds "
                                       f"{len(message)}")
            if summary.vehicle_id != vid or summary.kind != kind:
                raise Rejected("key", f"a {summary.kind} of vehicle {summary.vehicle_id} published "
                                      f"under {key}")
            status = self._accept(Arrival(memoryview(message), 1, None, f"zenoh:{key}",
                                          time.monotonic() - queued_at))
            self.counters[f"accepted_{kind}" if status == 0 else "stale"] += 1
            if kind == "delta" and status == 0:
                self.counters["bytes_in_delta"] += len(payload)
        except Rejected as e:
            if e.cause == "delta_base":  # we do not hold the map it applies to: fetch the full one
                self.counters["delta_refetch"] += 1
                self._want(str(vid))
                return
            self._drop(e.cause, vid, key, str(e))
        except Exception as e:  # a bug in the receive path must cost one message, not the link
            log.exception("zenoh: internal error receiving %s", key)
            self._drop("internal", vid, key, repr(e))

    def _drop(self, cause: str, vid: int | None, key: str, detail: str) -> None:
        self.counters[f"dropped_{cause}"] += 1
        self._failure(cause, vid, f"zenoh:{key}")
        self.drops.warn(f"zenoh:{key}", vid, cause, detail)

    def stats(self) -> dict:
        peers = []
        if self.session is not None:
            try:
                peers = [str(z) for z in self.session.info.peers_zid()]
            except Exception:  # closing
                peers = []
        return {"zid": None if self.session is None else str(self.session.zid()), "peers": peers,
                "swarm": self.settings.swarm, "mode": self.settings.mode, **dict(self.counters)}

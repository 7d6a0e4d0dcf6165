"""MTP over TCP: the map server (one listener, one bounded thread per connection) and the
sending side of a peer connection (hello, transfers, acks). Messages are opaque bytes here;
what a message means is decided by the `accept` callback the server is given."""

import logging
import os
import select
import socket
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

from coopd.net import family_of, host_port, listening_socket

from . import mtp, swarmkey
from .discovery import peer_address
from .mtp import Hello, MtpError, Offer, Proof, Reassembler, Transfer
from .peers import VEHICLE_IDS, PeerTable

log = logging.getLogger("coopd.sharing")

EVICT_WAIT_S = 1.0
"""How long a new connection waits for the slot of an idle connection evicted for it."""
SEND_CHUNK = 256 * 1024
"""Bytes per sendall: each chunk gets the write timeout, so a stalled receiver is noticed."""


class DropLog:
    """Warnings about dropped transfers, at most `burst` per remote address per `window_s`, so a
    hostile host cannot flood the journal; the next warning after a quiet window says how many
    were held back (the failure counters in `coopctl status` count every one)."""

    MAX_ADDRESSES = 1024

    def __init__(self, burst: int = 5, window_s: float = 60.0, clock=time.monotonic):
        self.burst, self.window_s, self._clock = burst, window_s, clock
        self._lock = threading.Lock()
        self._windows: dict[str, list] = {}  # address -> [window start, warned, held back]
        self.held_back = 0

    def warn(self, address: str, vehicle_id, cause: str, detail: str) -> bool:
        """Log one drop unless this address used up its burst; True if it was logged."""
        now = self._clock()
        with self._lock:
            w = self._windows.get(address)
            held = 0
            if w is None or now - w[0] >= self.window_s:
                held = 0 if w is None else w[2]
                if w is None and len(self._windows) >= self.MAX_ADDRESSES:
                    self._forget_old(now)
                w = self._windows[address] = [now, 0, 0]
            if w[1] >= self.burst:
                w[2] += 1
                self.held_back += 1
                return False
            w[1] += 1
        more = f" ({held} more from {address} not logged in the last window)" if held else ""
        log.warning("transfer from %s (vehicle %s) dropped: %s: %s%s", address, vehicle_id, cause, detail,
                    more)
        return True

    def _forget_old(self, now: float) -> None:
        for address, w in list(self._windows.items()):
            if now - w[0] >= self.window_s:
                del self._windows[address]
        if len(self._windows) >= self.MAX_ADDRESSES:  # all recent: forget the oldest half
            oldest = sorted(self._windows.items(), key=lambda kv: kv[1][0])[: self.MAX_ADDRESSES // 2]
            for address, _ in oldest:
                del self._windows[address]


@dataclass(frozen=True)
class TransportSettings:
    """Timeouts and bounds of both ends of a connection (docs/sharing.md, 'Settings')."""

    block_size: int = mtp.DEFAULT_BLOCK_SIZE
    connect_timeout: float = 0.5
    read_timeout: float = 5.0
    """Longest wait for any single read or write."""
    handshake_timeout: float = 3.0
    """A new connection must send its first frame within this time."""
    idle_timeout: float = 60.0
    """A connection with no transfer for this long is closed (the sender reconnects)."""
    transfer_base_s: float = 10.0
    min_rate: float = 128_000.0
    """Bytes/s: after transfer_base_s a transfer must have received at least min_rate bytes per
    second so far (so it ends by transfer_base_s + size / min_rate, and a trickle is cut early)."""
    max_connections: int = 32
    max_connections_per_address: int = 4
    """A single host flooding connections cannot take every slot."""
    max_bytes: int = 256 << 20
    """Largest transfer (data blocks) accepted."""
    max_cells: int = 400_000_000
    max_inflight_bytes: int = 512 << 20
    """Reassembly buffers of all concurrent transfers together."""
    swarm_key: bytes | None = None
    max_send_rate: float = 0.0
    """Bytes/s per peer link, 0 = unlimited: leaves room on a shared radio for other traffic."""

    def __post_init__(self):
        mtp.check_block_size(self.block_size)
        for name in ("connect_timeout", "read_timeout", "handshake_timeout", "idle_timeout",
                     "transfer_base_s", "min_rate"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be positive, got {getattr(self, name)}")
        for name in ("max_connections", "max_connections_per_address", "max_bytes", "max_cells",
                     "max_inflight_bytes"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be at least 1, got {getattr(self, name)}")
        if self.max_send_rate < 0:
            raise ValueError(f"max_send_rate must be >= 0, got {self.max_send_rate}")
        if self.swarm_key is not None and len(self.swarm_key) < 16:
            raise ValueError("swarm key must have at least 16 bytes")

    def transfer_deadline(self, nbytes: int) -> float:
        return self.transfer_base_s + nbytes / self.min_rate


REFUSAL_ACKS = {"version": mtp.ACK_VERSION, "delta_base": mtp.ACK_DELTA_BASE}
"""Refusal causes the sender is told apart from a plain refusal (ACK_REJECTED), by ack status."""
ROUTINE_REFUSALS = frozenset({"delta_base"})
"""Refusals that are part of the protocol, not a fault of the peer: counted, logged at info level, and
the connection stays open for what the sender sends next (a delta's base not held: the full map)."""


class Rejected(Exception):
    """A complete transfer whose content is refused; `cause` is the stats key."""

    def __init__(self, cause: str, message: str):
        super().__init__(message)
        self.cause = cause


@dataclass(frozen=True)
class Arrival:
    """A complete, authenticated transfer handed to the server's accept callback."""

    data: memoryview
    blocks: int
    peer_vehicle_id: int | None
    """From the connection hello; None for thesis-format peers (no hello)."""
    address: str
    seconds: float

    def take(self, size: int) -> bytes:
        """The first `size` bytes as an object of their own: the message itself when `data` views
        exactly that (a decrypted transfer), else a copy out of the receive buffer."""
        obj = self.data.obj
        if isinstance(obj, bytes) and len(obj) == size == self.data.nbytes:
            return obj
        return bytes(self.data[:size])


INFLIGHT_LEDGER = "sharing-inflight"
"""The memory budget's entry for the receive buffers of all transfers under way."""


class _Budget:
    """A byte budget shared by all reassembly buffers (max_inflight_bytes); with a ledger (the
    daemon's MemoryBudget) every byte is also charged there, so it counts against memory_mb."""

    def __init__(self, limit: int, ledger=None):
        self.limit, self.used, self.peak = limit, 0, 0
        self.ledger = ledger
        self._lock = threading.Lock()

    def reserve(self, n: int) -> bool:
        with self._lock:
            if self.used + n > self.limit:
                return False
            if self.ledger is not None and not self.ledger.add(INFLIGHT_LEDGER, n):
                return False
            self.used += n
            self.peak = max(self.peak, self.used)
            return True

    def release(self, n: int) -> None:
        with self._lock:
            self.used -= n
            if self.ledger is not None:
                self.ledger.add(INFLIGHT_LEDGER, -n)


class MapServer:
    """Receives transfers: every connection in its own thread, every read timed, every buffer bounded."""

    def __init__(self, settings: TransportSettings, vehicle_id: int, accept: Callable[[Arrival], int],
                 peers: PeerTable, host: str = "0.0.0.0", port: int = 0,
                 wants: Callable[[int, int], int] | None = None, ledger=None, deltas: bool = False):
        """deltas: the accept callback reads map deltas (wire type 4): say so in our hello replies."""
        self.settings = settings
        self.deltas = deltas
        self.vehicle_id = vehicle_id
        self._accept = accept
        self._wants = wants or (lambda origin, version: mtp.ACK_OK)
        """Answer to a relay offer: ACK_OK (send it) or ACK_STALE (already held)."""
        self.peers = peers
        self._bind = (host, port)
        self._listener: socket.socket | None = None
        self._stop = threading.Event()
        self._slots = threading.BoundedSemaphore(settings.max_connections)
        self._budget = _Budget(settings.max_inflight_bytes, ledger)
        self._conns: set[socket.socket] = set()
        self._receivers: set[_Connection] = set()
        self._per_address: dict[str, int] = {}
        self._threads: set[threading.Thread] = set()
        self._lock = threading.Lock()
        self._accept_thread: threading.Thread | None = None
        self.refused_busy = 0
        self.evicted_idle = 0
        self.accepted = 0
        self.drops = DropLog()
        self.instance = int.from_bytes(os.urandom(8), "little")
        """Random per server: tells peers this daemon restarted (and lost what it had received)."""

    @property
    def address(self) -> tuple[str, int]:
        return self._listener.getsockname()[:2]

    @property
    def inflight_bytes(self) -> int:
        return self._budget.used

    @property
    def peak_inflight_bytes(self) -> int:
        return self._budget.peak

    def receiving(self) -> list[dict]:
        """Transfers under way: who sends, and how far it got (coopctl status; tests cut links on it)."""
        with self._lock:
            receivers = list(self._receivers)
        out = []
        for c in receivers:
            reasm = c.reasm
            if reasm.in_transfer:
                out.append({"vehicle_id": c.vehicle_id, "address": c.address,
                            "received_bytes": reasm.received_bytes, "announced_bytes": reasm.announced_bytes})
        return out

    @property
    def open_connections(self) -> int:
        with self._lock:
            return len(self._conns)

    def start(self) -> "MapServer":
        ls = listening_socket(family_of(self._bind[0]), socket.SOCK_STREAM)
        try:
            ls.bind(self._bind)
        except OSError:
            ls.close()
            raise
        ls.listen(128)
        ls.settimeout(0.2)
        self._listener = ls
        self._accept_thread = threading.Thread(target=self._accept_loop, name="coopd-share-server",
                                               daemon=True)
        self._accept_thread.start()
        log.info("map server listening on %s (block size %d, key %s)", host_port(*self.address),
                 self.settings.block_size, "on" if self.settings.swarm_key else "off")
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._accept_thread is not None:
            self._accept_thread.join(2)
        if self._listener is not None:
            self._listener.close()
        with self._lock:
            for c in list(self._conns):
                try:
                    c.shutdown(socket.SHUT_RDWR)
                except OSError:
                    pass
            threads = list(self._threads)
        for t in threads:
            t.join(2)

    def _accept_loop(self) -> None:
        while not self._stop.is_set():
            try:
                conn, addr = self._listener.accept()
                addr = (peer_address(addr[0]), addr[1])
            except TimeoutError:
                continue
            except OSError:
                if self._stop.is_set():
                    return
                time.sleep(0.05)
                continue
            self.accepted += 1
            if not self._admit(addr[0]):
                self.refused_busy += 1
                self.peers.failure("busy", address=addr[0])
                conn.close()
                continue
            t = threading.Thread(target=self._serve, args=(conn, addr), name="coopd-share-conn", daemon=True)
            with self._lock:
                self._conns.add(conn)
                self._threads.add(t)
                self._per_address[addr[0]] = self._per_address.get(addr[0], 0) + 1
            t.start()

    def _admit(self, address: str) -> bool:
        """Take a slot for a new connection from `address`: a free one, or the slot of the connection
        idle the longest (unidentified ones first; one of the same address when that address is at its
        limit), evicted for it. Connections busy with a frame or a transfer are never evicted."""
        limit = self.settings.max_connections_per_address
        with self._lock:
            at_limit = self._per_address.get(address, 0) >= limit
        if not at_limit and self._slots.acquire(blocking=False):
            return True
        victim = self._idle_victim(address if at_limit else None)
        if victim is None:
            return False
        victim.evict()
        self.evicted_idle += 1
        deadline = time.monotonic() + EVICT_WAIT_S
        while time.monotonic() < deadline and not self._stop.is_set():
            with self._lock:
                at_limit = self._per_address.get(address, 0) >= limit
            if not at_limit and self._slots.acquire(timeout=0.05):
                return True
            if at_limit:
                time.sleep(0.01)
        return False

    def _idle_victim(self, address: str | None):
        with self._lock:
            idle = [c for c in self._receivers if c.idle_since is not None and not c.evicted
                    and (address is None or c.address == address)]
        if not idle:
            return None
        return min(idle, key=lambda c: (c.identified, c.idle_since))

    def _serve(self, conn: socket.socket, addr) -> None:
        receiver = _Connection(self, conn, addr[0])
        with self._lock:
            self._receivers.add(receiver)
        try:
            receiver.run()
        finally:
            conn.close()
            with self._lock:
                self._receivers.discard(receiver)
                self._conns.discard(conn)
                self._threads.discard(threading.current_thread())
                left = self._per_address.pop(addr[0], 1) - 1
                if left > 0:
                    self._per_address[addr[0]] = left
            self._slots.release()


class _Connection:
    """One accepted connection: hello (optional), then any number of transfers."""

    def __init__(self, server: MapServer, conn: socket.socket, address: str):
        self.server, self.conn, self.address = server, conn, address
        self.s = server.settings
        self.keyed = self.s.swarm_key is not None
        self.reasm = Reassembler(self.s.block_size, self.s.max_bytes,
                                 server._budget.reserve, server._budget.release, authorized=not self.keyed)
        self.hello: Hello | None = None
        self.identified = False
        """The hello's vehicle id is trusted: no swarm key, or the sender proved the key."""
        self.nonce = swarmkey.new_nonce()
        self.seq = 0
        self.cipher = None
        """The connection's transfer AEAD once a keyed sender proved the key (transfers are sealed)."""
        self.idle_since: float | None = time.monotonic()
        """Since when the connection waits for the peer between frames (None while a frame or a
        transfer is under way or being handled): the longest idle one is evicted when slots run out."""
        self.evicted = False

    def evict(self) -> None:
        """Close an idle connection to make room for a new one (its thread ends at once)."""
        self.evicted = True
        try:
            self.conn.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass

    @property
    def vehicle_id(self) -> int | None:
        """The sender's vehicle id once trusted (failures before that are charged to the address)."""
        return self.hello.vehicle_id if self.identified else None

    def run(self) -> None:
        cause, detail = None, ""
        try:
            self._loop()
        except MtpError as e:
            cause, detail = e.cause, str(e)
            if e.cause == "block_size":
                self._refuse_with_hello()
        except Rejected as e:
            cause, detail = e.cause, str(e)
        except TimeoutError as e:
            cause, detail = "timeout", str(e) or "read timed out"
        except OSError as e:
            cause, detail = "cut", f"connection error: {e}"
        except Exception as e:  # a bug in a callback must cost one transfer, not the server
            log.exception("internal error while receiving from %s", self.address)
            cause, detail = "internal", repr(e)
        finally:
            self.reasm.close()
        if self.evicted:
            cause, detail = "evicted", "idle connection closed to make room for a new one (all slots taken)"
        elif self.keyed and self.hello is not None and not self.reasm.authorized \
                and cause in (None, "timeout", "cut"):
            why = (f"its protocol version {self.hello.version} < {mtp.PROOF_VERSION} has no proof"
                   if self.hello.version < mtp.PROOF_VERSION else
                   "a wrong key, or it stopped waiting for our hello: a handshake timeout on a loaded host")
            cause, detail = "auth", (f"the peer claiming vehicle {self.hello.vehicle_id} left after its "
                                     f"hello without proving the swarm key ({why})")
        if cause is not None:
            self.server.peers.failure(cause, self.vehicle_id, self.address)
            self.server.drops.warn(self.address, self.vehicle_id, cause, detail)

    def _loop(self) -> None:
        s = self.s
        stop = self.server._stop
        deadline = time.monotonic() + s.handshake_timeout
        phase = "handshake"
        t_start = 0.0
        while not stop.is_set():
            now = time.monotonic()
            if phase == "transfer":  # keep up at least min_rate after the base time, all along
                deadline = t_start + s.transfer_base_s + self.reasm.received_bytes / s.min_rate
            if now >= deadline:
                if phase == "idle" and self.reasm.between_transfers:
                    log.info("closing idle connection from %s (vehicle %s)", self.address, self.vehicle_id)
                    return
                raise TimeoutError(f"{phase} deadline passed after {self.reasm.received_bytes} bytes")
            self.conn.settimeout(min(s.read_timeout, deadline - now))
            try:
                with self.reasm.buffer() as buf:  # released at once: the buffer may grow for the next read
                    n = self.conn.recv_into(buf)
            except TimeoutError:
                if self.reasm.between_transfers:
                    continue  # quiet between transfers: only the phase deadline applies
                raise TimeoutError(f"no data for {s.read_timeout} s after {self.reasm.received_bytes} "
                                   f"of {self.reasm.announced_bytes} bytes") from None
            if n == 0:
                if not self.reasm.between_transfers:
                    raise MtpError("cut", f"connection closed mid-transfer after {self.reasm.received_bytes} "
                                          f"of {self.reasm.announced_bytes} bytes")
                return
            was_in = self.reasm.in_transfer
            self.idle_since = None
            events = self.reasm.commit(n)
            if phase == "idle" and not self.reasm.between_transfers:
                phase = "frame"  # a control frame has begun: base transfer time, not the idle time
                deadline = min(deadline, time.monotonic() + s.transfer_base_s)
            if self.reasm.in_transfer and not was_in:
                t_start = time.monotonic()
                phase = "transfer"
                deadline = t_start + s.transfer_deadline(self.reasm.announced_bytes)
            for ev in events:
                if isinstance(ev, Hello):
                    self._on_hello(ev)
                    if self.keyed:  # the proof must follow at once: no slot is held by a hello alone
                        phase, deadline = "proof", time.monotonic() + s.handshake_timeout
                    else:
                        phase, deadline = "idle", time.monotonic() + s.idle_timeout
                elif isinstance(ev, Proof):
                    self._on_proof(ev)
                    phase, deadline = "idle", time.monotonic() + s.idle_timeout
                elif isinstance(ev, Transfer):
                    self._on_transfer(ev, time.monotonic() - t_start)
                    phase, deadline = "idle", time.monotonic() + s.idle_timeout
                elif isinstance(ev, Offer):
                    self._ack(0, self.server._wants(ev.origin, ev.version))
                    phase, deadline = "idle", time.monotonic() + s.idle_timeout
            if self.reasm.between_transfers:
                self.idle_since = time.monotonic()

    def _refuse_with_hello(self) -> None:
        """Tell a peer with another block size ours (so it fails clearly too), then close gently."""
        s = self.s
        try:
            self._send(mtp.hello_frame(Hello(s.block_size, self.server.vehicle_id, self.nonce,
                                             s.swarm_key is not None, self.server.instance)))
            self.conn.shutdown(socket.SHUT_WR)
            self.conn.settimeout(0.2)
            for _ in range(64):  # bounded drain so close() does not reset before the peer reads
                if not self.conn.recv(65536):
                    break
        except OSError:
            pass

    def _on_hello(self, hello: Hello) -> None:
        s = self.s
        if hello.vehicle_id not in VEHICLE_IDS:
            raise Rejected("vehicle_id", f"hello claims vehicle id {hello.vehicle_id}, outside "
                                         f"{VEHICLE_IDS.start}..{VEHICLE_IDS.stop - 1}")
        self.hello = hello
        keyed = s.swarm_key is not None
        tag = None
        if keyed:  # prove we hold the key: the sender trusts our vehicle id only then
            tag = swarmkey.hello_tag(s.swarm_key, hello.nonce, self.nonce, self.server.vehicle_id,
                                     self.server.instance, s.block_size, mtp.PROTOCOL_VERSION)
        reply = Hello(s.block_size, self.server.vehicle_id, self.nonce, keyed, self.server.instance, tag=tag,
                      deltas=self.server.deltas)
        self._send(mtp.hello_frame(reply))
        if hello.keyed != keyed:
            raise Rejected("auth", f"swarm key mismatch: peer key {'on' if hello.keyed else 'off'}, "
                                   f"ours {'on' if keyed else 'off'}")
        if not keyed:  # keyed: the sender's vehicle id counts once its proof verified
            self._seen()

    def _on_proof(self, proof: Proof) -> None:
        """A keyed sender's proof over both nonces: only now may it start a transfer or offer."""
        s, hello = self.s, self.hello
        expected = swarmkey.proof_tag(s.swarm_key, self.nonce, hello.nonce, hello.vehicle_id, hello.instance,
                                      s.block_size)
        if proof.vehicle_id != hello.vehicle_id or not swarmkey.tag_is_valid(expected, proof.tag):
            raise Rejected("auth", f"invalid proof of the swarm key from the peer claiming vehicle "
                                   f"{hello.vehicle_id}")
        self.reasm.authorized = True
        self.cipher = swarmkey.transfer_cipher(s.swarm_key, self.nonce, hello.nonce)
        self._seen()

    def _seen(self) -> None:
        """The peer is who its hello says (no key, or its first transfer verified): count it seen."""
        vid = self.hello.vehicle_id
        if vid != self.server.vehicle_id and not self.identified:  # not our own scan reaching us
            self.server.peers.seen(vid)
            log.info("peer vehicle %d connected from %s", vid, self.address)
        self.identified = True

    def _on_transfer(self, t: Transfer, seconds: float) -> None:
        """Check the tag, hand the transfer on, ack; its buffer stays charged to the in-flight budget
        until the server is done with it (a decode, a store), and is given back before the ack."""
        try:
            status = self._check_and_accept(t, seconds)
        except Rejected as e:
            self.server._budget.release(t.reserved)
            routine = e.cause in ROUTINE_REFUSALS and self.hello is not None
            if routine:  # counted before the ack, like any refusal, but the connection stays
                self.server.peers.failure(e.cause, self.vehicle_id, self.address)
                log.info("transfer from %s (vehicle %s) refused: %s: %s", self.address, self.vehicle_id,
                         e.cause, e)
            self._ack(t.blocks, REFUSAL_ACKS.get(e.cause, mtp.ACK_REJECTED))
            if not routine:
                raise
            return
        self.server._budget.release(t.reserved)
        self._ack(t.blocks, status)

    def _check_and_accept(self, t: Transfer, seconds: float) -> int:
        s = self.s
        seq = self.seq
        self.seq += 1
        if s.swarm_key is not None:
            expected = swarmkey.transfer_tag(s.swarm_key, self.nonce, self.hello.nonce, seq, t.blocks, t.data)
            if not swarmkey.tag_is_valid(expected, t.tag):
                raise Rejected("auth", "missing or invalid HMAC tag" if t.tag else "transfer has no HMAC tag")
        if self.cipher is None:
            arrival = Arrival(t.data, t.blocks, self.vehicle_id, self.address, seconds)
        else:
            try:
                message = swarmkey.unseal(self.cipher, seq, t.data)
            except ValueError as e:
                raise Rejected("auth", str(e)) from None
            arrival = Arrival(memoryview(message), t.blocks, self.vehicle_id, self.address, seconds)
        return self.server._accept(arrival)

    def _ack(self, blocks: int, status: int) -> None:
        if self.hello is not None:
            self._send(mtp.ack_frame(blocks, status, self.s.block_size))

    def _send(self, data: bytes) -> None:
        self.conn.settimeout(self.s.read_timeout)
        self.conn.sendall(data)


class PeerLink:
    """Our side of a connection to a peer's map server: hello exchange, then transfers with acks."""

    def __init__(self, sock: socket.socket, settings: TransportSettings, vehicle_id: int, address: str = "",
                 instance: int = 0, deltas: bool = False):
        self.instance = instance
        self.deltas = deltas
        """Our hello says we read map deltas (what our server accepts)."""
        self.wire_bytes_sent = 0
        """Bytes of every frame and data block this link sent (TCP/IP headers not counted)."""
        self.sock = sock
        self.s = settings
        self.vehicle_id = vehicle_id
        self.address = address
        self.nonce = swarmkey.new_nonce()
        self.peer: Hello | None = None
        self.seq = 0
        self.cipher = None
        """Transfers are sealed with it once we proved the key to a server of protocol 3 or later."""

    @classmethod
    def connect(cls, host: str, port: int, settings: TransportSettings, vehicle_id: int,
                source: str | None = None) -> "PeerLink":
        sock = socket.create_connection((host, port), timeout=settings.connect_timeout,
                                        source_address=(source, 0) if source else None)
        link = cls(sock, settings, vehicle_id, host)
        try:
            link.handshake()
        except BaseException:
            sock.close()
            raise
        return link

    def handshake(self) -> Hello:
        """Send our hello, read theirs; MtpError on a block size or swarm key mismatch."""
        s = self.s
        self.sock.settimeout(s.read_timeout)
        self.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        _keepalive(self.sock)
        self.sock.sendall(mtp.hello_frame(Hello(s.block_size, self.vehicle_id, self.nonce,
                                                s.swarm_key is not None, self.instance, deltas=self.deltas)))
        self.wire_bytes_sent += s.block_size
        head = self._recv_exact(mtp.HEAD.size, s.handshake_timeout)
        marker, kind, bs = mtp.HEAD.unpack(head)
        if marker != mtp.MARK or kind != mtp.HELLO:
            raise MtpError("frame", f"peer did not answer with a hello (bytes {head[:2].hex()})")
        if bs != s.block_size:
            raise MtpError("block_size", f"peer uses block size {bs}, this end uses {s.block_size}; "
                                         f"both ends must agree (setting sharing.block_size)")
        frame = head + self._recv_exact(bs - mtp.HEAD.size, s.handshake_timeout)
        peer = mtp.parse_hello(frame)
        if peer.keyed != (s.swarm_key is not None):
            raise MtpError("auth", f"swarm key mismatch: peer key {'on' if peer.keyed else 'off'}, "
                                   f"ours {'on' if s.swarm_key else 'off'}")
        if s.swarm_key is not None:
            expected = swarmkey.hello_tag(s.swarm_key, self.nonce, peer.nonce, peer.vehicle_id,
                                          peer.instance, bs, peer.version)
            if not swarmkey.tag_is_valid(expected, peer.tag):
                raise MtpError("auth", f"peer claiming vehicle {peer.vehicle_id} did not prove the swarm key "
                                       f"in its hello ({'invalid' if peer.tag else 'no'} tag; protocol "
                                       f"version {peer.version}, ours {mtp.PROTOCOL_VERSION})")
            if peer.version >= mtp.PROOF_VERSION:  # our proof, before the server accepts anything else
                tag = swarmkey.proof_tag(s.swarm_key, peer.nonce, self.nonce, self.vehicle_id, self.instance,
                                         bs)
                self.sock.sendall(mtp.proof_frame(self.vehicle_id, tag, bs))
                self.wire_bytes_sent += bs
                self.cipher = swarmkey.transfer_cipher(s.swarm_key, peer.nonce, self.nonce)
        self.peer = peer  # set only once the handshake succeeded
        return peer

    def send_map(self, message) -> tuple[int, float]:
        """Send one message as an MTP transfer; return (ack status, seconds until the ack)."""
        s = self.s
        bs = s.block_size
        if self.cipher is not None:
            message = swarmkey.seal(self.cipher, self.seq, message)
        view = memoryview(message).cast("B")
        blocks = mtp.block_count(len(view), bs)
        pad = blocks * bs - len(view)
        tag = None
        if s.swarm_key is not None:
            tag = swarmkey.transfer_tag(s.swarm_key, self.peer.nonce, self.nonce, self.seq, blocks, view, pad)
        self.seq += 1
        t0 = time.monotonic()
        self.sock.settimeout(s.read_timeout)
        self.sock.sendall(mtp.start_frame(blocks, bs))
        rate = s.max_send_rate
        step = SEND_CHUNK if rate <= 0 else int(min(SEND_CHUNK, max(bs, rate / 20)))
        sent = 0
        for chunk in mtp.data_chunks(view, bs):
            cv = memoryview(chunk)
            for i in range(0, len(cv), step):
                self.sock.sendall(cv[i:i + step])
                sent += len(cv[i:i + step])
                if rate > 0:
                    ahead = sent / rate - (time.monotonic() - t0)
                    if ahead > 0:
                        time.sleep(ahead)
        self.sock.sendall(mtp.stop_frame(blocks, bs, tag))
        self.wire_bytes_sent += (blocks + 2) * bs
        ack = self._recv_exact(bs, s.transfer_deadline(blocks * bs))
        got, status = mtp.parse_ack(ack)
        if got != blocks:
            raise MtpError("count", f"peer acknowledged {got} blocks, we sent {blocks}")
        return status, time.monotonic() - t0

    def offer(self, origin: int, version: int) -> int:
        """Ask whether the peer needs `origin`'s map at `version` (ACK_OK) or holds it (ACK_STALE)."""
        self.sock.settimeout(self.s.read_timeout)
        self.sock.sendall(mtp.offer_frame(origin, version, self.s.block_size))
        self.wire_bytes_sent += self.s.block_size
        blocks, status = mtp.parse_ack(self._recv_exact(self.s.block_size, self.s.read_timeout))
        if blocks != 0:
            raise MtpError("count", f"peer answered an offer with an ack for {blocks} blocks")
        return status

    def closed_by_peer(self) -> bool:
        """True if the peer closed the connection (checked without blocking)."""
        try:
            r, _, _ = select.select([self.sock], [], [], 0)
            if not r:
                return False
            return self.sock.recv(1, socket.MSG_PEEK) == b""
        except OSError:
            return True

    def close(self) -> None:
        try:
            self.sock.close()
        except OSError:
            pass

    def _recv_exact(self, n: int, total_timeout: float) -> bytes:
        buf = bytearray(n)
        view = memoryview(buf)
        got = 0
        deadline = time.monotonic() + total_timeout
        while got < n:
            left = deadline - time.monotonic()
            if left <= 0:
                raise TimeoutError(f"peer sent {got} of {n} expected bytes in time")
            self.sock.settimeout(min(left, max(self.s.read_timeout, total_timeout)))
            k = self.sock.recv_into(view[got:])
            if k == 0:
                raise MtpError("cut", f"peer closed the connection after {got} of {n} bytes")
            got += k
        return bytes(buf)


def _keepalive(sock: socket.socket) -> None:
    """TCP keepalive with short intervals: a peer that vanishes while idle is noticed in ~6 s."""
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_KEEPALIVE, 1)
    for opt, val in (("TCP_KEEPIDLE", 3), ("TCP_KEEPINTVL", 1), ("TCP_KEEPCNT", 3)):
        if hasattr(socket, opt):
            sock.setsockopt(socket.IPPROTO_TCP, getattr(socket, opt), val)

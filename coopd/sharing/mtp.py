"""Map Transmission Protocol framing and reassembly (thesis §7.3, notes §6; docs/sharing.md).

Every frame is exactly BS bytes. A transfer is a start frame (0x80, 0, int32 block count),
the serialized message cut into BS-byte data blocks (the last zero-padded), and a stop frame
(0x80, 1, int32 block count). coopd extends the thesis with frames of its own that a thesis
sender never emits: a connection hello (0x80, 2), a transfer ack (0x80, 3), a relay offer
(0x80, 4) and a sender's proof of the swarm key (0x80, 5); and it may put
an HMAC tag in the stop frame's spare bytes, which the thesis leaves zero and ignores.

The Reassembler is a pure state machine over received bytes: a start frame is refused unless the
connection is authorized (keyed: the sender proved the key) and announces at most `max_bytes`;
the transfer's buffer is an anonymous mapping of the announced size whose pages become memory
only where data lands, charged step by step as data arrives, and any inconsistency raises
MtpError with a cause, after which the connection must be dropped.
"""

import mmap
import struct
from dataclasses import dataclass

MARK = 0x80
"""Byte 0 of every control frame (-128 as int8); never a cell value or a message type."""
START, STOP, HELLO, ACK, OFFER, PROOF = 0, 1, 2, 3, 4, 5
DEFAULT_BLOCK_SIZE = 4096
MIN_BLOCK_SIZE = 64
"""Small enough for any sane link, large enough for the hello and a stop frame with a tag."""
MAX_BLOCK_SIZE = 1 << 20
PROTOCOL_VERSION = 3
"""coopd's MTP extension version, carried in the hello (2: a keyed server signs its hello; 3: a
keyed sender proves the key with a proof frame before anything else)."""
PROOF_VERSION = 3
"""The first protocol version whose keyed senders send a proof frame."""

HEAD = struct.Struct("<BBi")
"""marker, frame type, int32 count: bytes 0-5 of every control frame."""
HELLO_BODY = struct.Struct("<BBi16sQ")
"""after HEAD (whose count is the sender's block size): protocol version, flags, vehicle id,
nonce, instance id (random per process start: a changed one means the peer lost its state)."""
OFFER_BODY = struct.Struct("<Q")
"""after HEAD (whose count is the origin vehicle id): the map version offered."""
HELLO_TAG = struct.Struct("<16s")
"""after HELLO_BODY (bytes 36-51): a keyed server's hello tag (swarmkey.hello_tag); zero otherwise."""
PROOF_TAG = struct.Struct("<16s")
"""after HEAD (whose count is the sender's vehicle id): the proof tag (swarmkey.proof_tag)."""
HELLO_FLAG_KEY = 0x01
HELLO_FLAG_DELTAS = 0x02
"""The hello's sender reads map deltas (wire type 4, coopd.sharing.delta); older coopds leave it 0 and
ignore it, so they are sent full maps only."""
TAG_HMAC_SHA256 = 0x01
"""Stop frame byte 6: a 32-byte HMAC-SHA256 tag follows in bytes 7-38."""
TAG_SIZE = 32
ACK_OK, ACK_STALE, ACK_REJECTED, ACK_VERSION, ACK_DELTA_BASE = 0, 1, 2, 3, 4
"""Ack status (byte 6 of an ack): stored; not newer than what the receiver holds; refused; refused
because its version is implausible (coopd.sharing.versions: the sender should start a new epoch);
a delta refused because the receiver does not hold the map it applies to (send the full map).
Senders older than protocol 3 read any status but 0 and 1 as refused; only senders that send deltas
get status 4."""
RESERVE_STEP = 256 * 1024
"""A transfer's buffer is charged to the in-flight budget in steps of this many bytes, each step
before data may land in it: what a transfer holds is what it sent, rounded up to one step."""


class MtpError(ValueError):
    """A transfer that breaks the protocol; `cause` is a short stats key (e.g. "count")."""

    def __init__(self, cause: str, message: str):
        super().__init__(message)
        self.cause = cause


@dataclass(frozen=True)
class Hello:
    """coopd's connection hello: who is talking, with which block size, and a fresh nonce."""

    block_size: int
    vehicle_id: int
    nonce: bytes
    keyed: bool
    instance: int = 0
    version: int = PROTOCOL_VERSION
    tag: bytes | None = None
    """A keyed server's proof that it holds the swarm key (the sender's hello carries none)."""
    deltas: bool = False
    """The sender of this hello reads map deltas (HELLO_FLAG_DELTAS)."""


@dataclass(frozen=True)
class Offer:
    """coopd's relay offer: 'I could send you vehicle `origin`'s map at `version`; do you need it?'"""

    origin: int
    version: int


@dataclass(frozen=True)
class Proof:
    """A keyed sender's proof that it holds the swarm key, over both nonces (swarmkey.proof_tag)."""

    vehicle_id: int
    tag: bytes


@dataclass(frozen=True)
class Transfer:
    """One complete, count-checked transfer: the data blocks (message + zero padding) and tag."""

    data: memoryview
    blocks: int
    tag: bytes | None
    reserved: int = 0
    """Bytes of the in-flight budget the buffer still holds: the receiver releases them once it
    handled the transfer (the reassembler's release callback)."""


def check_block_size(block_size: int) -> int:
    """The block size, if it is one both ends can use; ValueError otherwise."""
    if not (MIN_BLOCK_SIZE <= block_size <= MAX_BLOCK_SIZE):
        raise ValueError(f"block size {block_size} is outside [{MIN_BLOCK_SIZE}, {MAX_BLOCK_SIZE}]")
    return block_size


def _control(kind: int, count: int, block_size: int, extra: bytes = b"") -> bytes:
    frame = bytearray(block_size)
    HEAD.pack_into(frame, 0, MARK, kind, count)
    frame[HEAD.size:HEAD.size + len(extra)] = extra
    return bytes(frame)


def start_frame(blocks: int, block_size: int) -> bytes:
    """The thesis start frame announcing `blocks` data blocks."""
    return _control(START, blocks, block_size)


def stop_frame(blocks: int, block_size: int, tag: bytes | None = None) -> bytes:
    """The thesis stop frame; with a tag, bytes 6-38 carry (TAG_HMAC_SHA256, tag)."""
    if tag is None:
        return _control(STOP, blocks, block_size)
    if len(tag) != TAG_SIZE:
        raise ValueError(f"tag must be {TAG_SIZE} bytes, got {len(tag)}")
    return _control(STOP, blocks, block_size, bytes([TAG_HMAC_SHA256]) + tag)


def hello_frame(hello: Hello) -> bytes:
    """The hello frame; its count field is the sender's block size so a mismatch shows at once."""
    flags = (HELLO_FLAG_KEY if hello.keyed else 0) | (HELLO_FLAG_DELTAS if hello.deltas else 0)
    body = HELLO_BODY.pack(hello.version, flags, hello.vehicle_id, hello.nonce, hello.instance)
    if hello.tag is not None:
        if len(hello.tag) != HELLO_TAG.size:
            raise ValueError(f"hello tag must be {HELLO_TAG.size} bytes, got {len(hello.tag)}")
        body += HELLO_TAG.pack(hello.tag)
    return _control(HELLO, hello.block_size, hello.block_size, body)


def ack_frame(blocks: int, status: int, block_size: int) -> bytes:
    """The receiver's verdict on the transfer of `blocks` blocks just received."""
    return _control(ACK, blocks, block_size, bytes([status]))


def proof_frame(vehicle_id: int, tag: bytes, block_size: int) -> bytes:
    """A keyed sender's proof of the swarm key, sent right after the server's hello."""
    return _control(PROOF, vehicle_id, block_size, PROOF_TAG.pack(tag))


def offer_frame(origin: int, version: int, block_size: int) -> bytes:
    """Ask before relaying: the receiver answers with an ack (0 blocks): OK = send it, STALE = I have it."""
    return _control(OFFER, origin, block_size, OFFER_BODY.pack(version))


def block_count(size: int, block_size: int) -> int:
    """Data blocks needed for a message of `size` bytes."""
    return -(-size // block_size)


def data_chunks(message, block_size: int):
    """The data blocks of `message` as at most two buffers: the full blocks, then the padded tail."""
    view = memoryview(message).cast("B")
    full = len(view) - len(view) % block_size
    if full:
        yield view[:full]
    if full < len(view):
        yield bytes(view[full:]) + bytes(block_size - (len(view) - full))


def encode_transfer(message, block_size: int, tag: bytes | None = None) -> list:
    """All buffers of one transfer, in order (for tests and small messages)."""
    n = block_count(len(message), block_size)
    return [start_frame(n, block_size), *data_chunks(message, block_size), stop_frame(n, block_size, tag)]


def parse_hello(frame) -> Hello:
    """A hello frame (BS bytes, already known to start with MARK, HELLO)."""
    _, _, block_size = HEAD.unpack_from(frame)
    version, flags, vehicle_id, nonce, instance = HELLO_BODY.unpack_from(frame, HEAD.size)
    if version < 1:
        raise MtpError("frame", f"hello protocol version {version} does not exist")
    (tag,) = HELLO_TAG.unpack_from(frame, HEAD.size + HELLO_BODY.size)
    return Hello(block_size, vehicle_id, bytes(nonce), bool(flags & HELLO_FLAG_KEY), instance, version,
                 None if _all_zero(tag) else bytes(tag), bool(flags & HELLO_FLAG_DELTAS))


def parse_ack(frame) -> tuple[int, int]:
    """(blocks, status) of an ack frame; MtpError if it is not one."""
    marker, kind, blocks = HEAD.unpack_from(frame)
    if marker != MARK or kind != ACK:
        raise MtpError("frame", f"expected an ack frame, got bytes {bytes(frame[:2]).hex()}")
    return blocks, frame[HEAD.size]


def _all_zero(view) -> bool:
    return not any(view) if len(view) < 64 else bytes(view).count(0) == len(view)


def _stop_tag(frame, block_size: int):
    """(ok, tag) for the spare bytes of a stop frame: all zero, or a tag then zeros."""
    rest = memoryview(frame)[HEAD.size:block_size]
    if rest[0] == 0:
        return _all_zero(rest), None
    if rest[0] == TAG_HMAC_SHA256 and len(rest) >= 1 + TAG_SIZE:
        return _all_zero(rest[1 + TAG_SIZE:]), bytes(rest[1:1 + TAG_SIZE])
    return False, None


class Reassembler:
    """Receiver state machine: bytes in (via buffer()/commit() or feed()), hello and transfers out.

    buffer() returns the writable view the next bytes belong in (so a socket can recv_into it
    without copies); commit(n) processes n bytes written there. Each call returns the events
    completed (Hello or Transfer objects) and raises MtpError on any protocol violation.
    """

    _HEAD, _REST, _DATA = 0, 1, 2

    def __init__(self, block_size: int = DEFAULT_BLOCK_SIZE, max_bytes: int = 512 << 20,
                 reserve=None, release=None, authorized: bool = True):
        self.block_size = check_block_size(block_size)
        self.authorized = authorized
        """Start and offer frames are accepted (a keyed receiver sets it once the sender proved the key)."""
        self.max_bytes = max_bytes
        self._reserve = reserve
        self._release = release
        self._frame = bytearray(block_size)
        self._state = self._HEAD
        self._filled = 0
        self._kind = -1
        self._announced = 0
        self._data: mmap.mmap | None = None
        self._reserved = 0
        self._usable = 0
        """Bytes of the transfer's buffer that may receive data (charged to the budget so far)."""
        self._received_blocks = 0
        self.frames_seen = 0
        self.saw_hello = False

    @property
    def in_transfer(self) -> bool:
        """True between a start frame and its stop frame."""
        return self._announced > 0

    @property
    def between_transfers(self) -> bool:
        """True when nothing is half-received: no transfer open, no partial frame."""
        return self._announced == 0 and self._state == self._HEAD and self._filled == 0

    @property
    def announced_bytes(self) -> int:
        return self._announced * self.block_size

    @property
    def received_bytes(self) -> int:
        return self._filled if self._state == self._DATA else self._received_blocks * self.block_size

    def buffer(self) -> memoryview:
        """Where the next received bytes go (never longer than what the current state needs)."""
        if self._state == self._HEAD:
            return memoryview(self._frame)[self._filled:HEAD.size]
        if self._state == self._REST:
            return memoryview(self._frame)[self._filled:]
        if self._filled == self._usable:
            self._charge_step()
        return memoryview(self._data)[self._filled:self._usable]

    def _charge_step(self) -> None:
        """Let the next RESERVE_STEP bytes (at most up to the announced size) receive data, charged first."""
        step = min(self._announced * self.block_size, self._usable + RESERVE_STEP) - self._usable
        if self._reserve is not None:
            if not self._reserve(step):
                self._fail("busy", f"no room for {step} more bytes of concurrent transfers (this one "
                                   f"received {self._usable} of {self._announced * self.block_size})")
            self._reserved += step
        self._usable += step

    def commit(self, n: int) -> list:
        """Account for n bytes written into buffer(); return completed events."""
        self._filled += n
        if self._state == self._HEAD:
            if self._filled == HEAD.size:
                self._on_head()
            return []
        if self._state == self._REST:
            if self._filled == self.block_size:
                return self._on_control()
            return []
        self._check_early_stop(n)
        self._received_blocks = self._filled // self.block_size
        if self._filled == self._announced * self.block_size:
            self._state, self._filled = self._HEAD, 0
        return []

    def feed(self, data) -> list:
        """Process `data` (any length); return the events it completes."""
        view = memoryview(data).cast("B")
        events = []
        while len(view):
            target = self.buffer()
            n = min(len(target), len(view))
            target[:n] = view[:n]
            target.release()  # the buffer may grow on the next call
            view = view[n:]
            events += self.commit(n)
        return events

    def close(self) -> None:
        """Release the reassembly buffer (a cut transfer is simply forgotten)."""
        self._drop_data()

    def _drop_data(self) -> None:
        if self._reserved and self._release is not None:
            self._release(self._reserved)
        self._reserved = 0
        self._data = None
        self._announced = 0

    def _fail(self, cause: str, message: str):
        self._drop_data()
        raise MtpError(cause, message)

    def _on_head(self) -> None:
        marker, kind, count = HEAD.unpack_from(self._frame)
        if marker != MARK:
            if self._data is not None:
                self._fail("count", f"more data blocks than the {self._announced} announced "
                                    f"(byte 0x{marker:02x} where the stop frame belongs)")
            self._fail("frame", f"expected a control frame (0x80), got byte 0x{marker:02x}: not MTP")
        if self._data is not None and kind != STOP:
            self._fail("count", f"frame type {kind} after {self._announced} data blocks; "
                                f"expected the stop frame")
        if kind in (START, OFFER) and not self.authorized:
            self._fail("auth", f"{'start' if kind == START else 'offer'} frame before the sender proved "
                               f"the swarm key")
        if kind == START:
            if count <= 0:
                self._fail("frame", f"start frame announces {count} blocks")
            if count * self.block_size > self.max_bytes:
                self._fail("oversize", f"start frame announces {count} blocks of {self.block_size} bytes "
                                       f"({count * self.block_size} bytes), limit {self.max_bytes}")
        elif kind == HELLO:
            if self.frames_seen:
                self._fail("frame", "hello frame in the middle of a connection")
            if count != self.block_size:
                self._fail("block_size", f"peer uses block size {count}, this end uses {self.block_size}; "
                                         f"both ends must agree (setting sharing.block_size)")
        elif kind == STOP:
            if self._data is None:
                self._fail("count", f"stop frame ({count} blocks) without a start frame")
        elif kind == ACK:
            self._fail("frame", "ack frame sent to a receiver")
        elif kind == OFFER:
            if not self.saw_hello:
                self._fail("frame", "offer frame without a hello")
        elif kind == PROOF:
            if not self.saw_hello or self.authorized:
                self._fail("frame", "proof frame without a hello or after the proof")
        else:
            self._fail("frame", f"unknown control frame type {kind}")
        self._kind, self._count = kind, count
        self._state = self._REST

    def _on_control(self) -> list:
        self.frames_seen += 1
        self._state, self._filled = self._HEAD, 0
        if self._kind == START:
            rest = memoryview(self._frame)[HEAD.size:]
            if not _all_zero(rest):
                self._fail("frame", "start frame padding is not zero; does the peer use another block size?")
            self._data = mmap.mmap(-1, self._count * self.block_size)  # address space, not memory
            self._usable = 0
            self._reserved = 0
            self._announced = self._count
            self._received_blocks = 0
            self._state = self._DATA
            return []
        if self._kind == HELLO:
            self.saw_hello = True
            return [parse_hello(self._frame)]
        if self._kind == PROOF:
            (tag,) = PROOF_TAG.unpack_from(self._frame, HEAD.size)
            if not _all_zero(memoryview(self._frame)[HEAD.size + PROOF_TAG.size:]):
                self._fail("frame", "proof frame padding is not zero")
            return [Proof(self._count, bytes(tag))]
        if self._kind == OFFER:
            (version,) = OFFER_BODY.unpack_from(self._frame, HEAD.size)
            if not _all_zero(memoryview(self._frame)[HEAD.size + OFFER_BODY.size:]):
                self._fail("frame", "offer frame padding is not zero")
            return [Offer(self._count, version)]
        # STOP
        ok, tag = _stop_tag(self._frame, self.block_size)
        if not ok:
            self._fail("frame", "stop frame spare bytes are malformed; does the peer use another block size?")
        if not (self._count == self._announced == self._received_blocks):
            self._fail("count", f"start announced {self._announced} blocks, stop says {self._count}, "
                                f"received {self._received_blocks}")
        transfer = Transfer(memoryview(self._data), self._announced, tag, self._reserved)
        self._data = None
        self._announced = 0
        self._reserved = 0  # handed on with the transfer: the receiver releases it when done
        return [transfer]

    def _check_early_stop(self, n: int) -> None:
        """A data block that is exactly a stop frame for the blocks before it: the sender mis-counted."""
        bs = self.block_size
        data = self._data
        for j in range((self._filled - n) // bs, self._filled // bs):
            if data[j * bs] != MARK:
                continue
            block = memoryview(data)[j * bs:(j + 1) * bs]
            marker, kind, count = HEAD.unpack_from(block)
            if kind == STOP and count == j and _stop_tag(block, bs)[0]:
                self._fail("count", f"stop frame after {j} data blocks, start announced {self._announced}")

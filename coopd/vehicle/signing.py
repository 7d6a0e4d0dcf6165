"""Optional MAVLink 2 signing on the FC link: our messages signed, the FC's accepted only with a
valid signature under the shared 32-byte key (docs/vehicle.md, "Signing").

pymavlink's own check records a stream's timestamp before it verifies the signature, so one forged
packet with the FC's ids and a far-future timestamp would make every later genuine message look
like a replay, and forged streams would grow its table without bound. StreamSigning verifies the
signature first and keeps at most MAX_STREAMS streams.
"""

from __future__ import annotations

import hashlib
import hmac
import string
import struct
import time

KEY_BYTES = 32
EPOCH_2015 = 1420070400
"""MAVLink signing timestamps count 10 µs units since 2015-01-01 00:00 UTC."""
NEW_STREAM_SLACK = 60 * 100_000
"""A new stream's first timestamp may be up to one minute behind ours (the MAVLink rule)."""
MAX_STREAMS = 64
MAX_KEY_FILE_BYTES = 4096


def read_signing_key(path: str) -> bytes:
    """The key in a signing key file: 64 hexadecimal characters (32 bytes), surrounding whitespace
    ignored; ValueError or OSError saying what is wrong."""
    with open(path, "rb") as f:
        data = f.read(MAX_KEY_FILE_BYTES + 1)
    text = data.decode("ascii", "replace").strip()
    if len(data) > MAX_KEY_FILE_BYTES or len(text) != 2 * KEY_BYTES or not set(text) <= set(string.hexdigits):
        raise ValueError(
            f"{path}: a MAVLink signing key file holds {2 * KEY_BYTES} hexadecimal characters "
            "(e.g. made with `openssl rand -hex 32`)"
        )
    return bytes.fromhex(text)


def signing_timestamp(unix_s: float) -> int:
    return max(0, int((unix_s - EPOCH_2015) * 100_000))


class StreamSigning:
    """Installs signing on a pymavlink MAVLink object and checks incoming signatures for it."""

    _TIMESTAMP = struct.Struct("<IH")

    def __init__(self, mav, key: bytes, link_id: int = 0):
        if len(key) != KEY_BYTES:
            raise ValueError(f"a MAVLink signing key has {KEY_BYTES} bytes, got {len(key)}")
        self.mav = mav
        self.streams: dict[tuple[int, int, int], int] = {}
        s = mav.signing
        s.secret_key = key
        s.link_id = link_id
        s.timestamp = signing_timestamp(time.time())
        s.sign_outgoing = True
        s.allow_unsigned_callback = lambda _mav, _msg_id: False  # counts rejects in reject_count
        mav.check_signature = self.check

    def check(self, msgbuf, src_system: int, src_component: int) -> bool:
        """pymavlink's check_signature contract: True accepts the (signed) message."""
        s = self.mav.signing
        digest = hashlib.sha256(s.secret_key + bytes(msgbuf[:-6])).digest()[:6]
        if not hmac.compare_digest(digest, bytes(msgbuf[-6:])):
            return False
        low, high = self._TIMESTAMP.unpack(bytes(msgbuf[-12:-6]))
        timestamp = low + (high << 32)
        stream = (msgbuf[-13], src_system, src_component)
        last = self.streams.get(stream)
        if last is not None and timestamp <= last:
            return False  # a replay
        if last is None and timestamp + NEW_STREAM_SLACK < s.timestamp:
            return False  # a new stream from the past: a recording
        if last is None and len(self.streams) >= MAX_STREAMS:
            del self.streams[min(self.streams, key=self.streams.get)]
        self.streams[stream] = timestamp
        s.timestamp = max(s.timestamp, timestamp)
        return True

    def counters(self) -> dict:
        s = self.mav.signing
        return {
            "signed_ok": s.goodsig_count,
            "signature_bad": s.badsig_count,
            "unsigned_rejected": s.reject_count - s.badsig_count,
        }

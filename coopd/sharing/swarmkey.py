"""The optional swarm key: an HMAC-SHA256 tag per transfer, bound to the connection's nonces
and the transfer's sequence number so a recorded transfer cannot be replayed, a tag on a
server's hello so that no host without the key can pose as a vehicle's map server, a sender's
proof of the key, and the encryption of transfers (ChaCha20-Poly1305 under a key derived per
connection with HKDF-SHA256 from the swarm key and both nonces) (docs/sharing.md)."""

import hashlib
import hmac
import os
import struct

CONTEXT = b"coopd-mtp/1 transfer"
HELLO_CONTEXT = b"coopd-mtp/2 hello"
PROOF_CONTEXT = b"coopd-mtp/3 proof"
HELLO_TAG_SIZE = 16
"""HMAC-SHA256 truncated to 128 bits: it fits a hello in the smallest block (64 bytes)."""
NONCE_SIZE = 16


def new_nonce() -> bytes:
    return os.urandom(NONCE_SIZE)


def load_key(value: str | bytes | None) -> bytes | None:
    """The key from a config value: None/empty for no key, 'hex:...' or a passphrase string."""
    if not value:
        return None
    if isinstance(value, bytes):
        key = value
        if not key:
            return None
    elif value.startswith("hex:"):
        key = bytes.fromhex(value[4:])
    else:
        key = value.encode()
    if len(key) < 16:
        raise ValueError(f"swarm key must have at least 16 bytes, got {len(key)}")
    return key


MAX_KEY_FILE_BYTES = 4096


def read_key_file(path) -> bytes | None:
    """The swarm key from a file (the daemon's swarm_key_file): its bytes without surrounding
    whitespace; 'hex:...' content is decoded. None for an empty path."""
    if not path:
        return None
    with open(path, "rb") as f:
        data = f.read(MAX_KEY_FILE_BYTES + 1)
    if len(data) > MAX_KEY_FILE_BYTES:
        raise ValueError(f"swarm key file {path} is larger than {MAX_KEY_FILE_BYTES} bytes")
    data = data.strip()
    return load_key(data.decode("ascii") if data.startswith(b"hex:") else data)


def transfer_tag(key: bytes, receiver_nonce: bytes, sender_nonce: bytes, seq: int, blocks: int,
                 message, padding: int = 0) -> bytes:
    """HMAC-SHA256 over context, nonces, sequence, block count and the data blocks as sent."""
    mac = hmac.new(key, CONTEXT + receiver_nonce + sender_nonce + struct.pack("<QI", seq, blocks),
                   hashlib.sha256)
    mac.update(message)
    if padding:
        mac.update(bytes(padding))
    return mac.digest()


def hello_tag(key: bytes, sender_nonce: bytes, server_nonce: bytes, vehicle_id: int, instance: int,
              block_size: int, version: int) -> bytes:
    """A server's hello tag: HMAC-SHA256 over context, the sender's nonce (fresh, so a recorded
    hello cannot be replayed), the server's nonce and every field of its hello, truncated."""
    mac = hmac.new(key, HELLO_CONTEXT + sender_nonce + server_nonce
                   + struct.pack("<iQiB", vehicle_id, instance, block_size, version), hashlib.sha256)
    return mac.digest()[:HELLO_TAG_SIZE]


def proof_tag(key: bytes, server_nonce: bytes, sender_nonce: bytes, vehicle_id: int, instance: int,
              block_size: int) -> bytes:
    """A sender's proof of the key: HMAC-SHA256 over context, the server's nonce (fresh, so a
    recorded proof cannot be replayed), the sender's nonce and its hello's fields, truncated."""
    mac = hmac.new(key, PROOF_CONTEXT + server_nonce + sender_nonce
                   + struct.pack("<iQi", vehicle_id, instance, block_size), hashlib.sha256)
    return mac.digest()[:HELLO_TAG_SIZE]


TRANSFER_KEY_INFO = b"coopd-mtp/3 transfer encryption"
SEAL_HEAD = struct.Struct("<I")
"""A sealed message starts with the byte length of the ciphertext (which includes the 16-byte tag)."""
SEAL_OVERHEAD = SEAL_HEAD.size + 16


def transfer_cipher(key: bytes, server_nonce: bytes, sender_nonce: bytes):
    """The AEAD of one connection's transfers (sender to server): ChaCha20-Poly1305 under
    HKDF-SHA256(swarm key, salt = server nonce ‖ sender nonce). Both nonces are fresh per
    connection, so every connection has its own key and a transfer's sequence number is its nonce."""
    from cryptography.hazmat.primitives import hashes
    from cryptography.hazmat.primitives.ciphers.aead import ChaCha20Poly1305
    from cryptography.hazmat.primitives.kdf.hkdf import HKDF

    derived = HKDF(algorithm=hashes.SHA256(), length=32, salt=server_nonce + sender_nonce,
                   info=TRANSFER_KEY_INFO).derive(key)
    return ChaCha20Poly1305(derived)


def _aead_nonce(seq: int) -> bytes:
    return struct.pack("<4xQ", seq)


def seal(cipher, seq: int, message) -> bytes:
    """The message encrypted and authenticated as transfer `seq` of the connection."""
    sealed = cipher.encrypt(_aead_nonce(seq), bytes(message), None)
    return SEAL_HEAD.pack(len(sealed)) + sealed


def unseal(cipher, seq: int, data) -> bytes:
    """The message of a sealed transfer (data: its blocks, zero padding after the ciphertext);
    ValueError if it is not transfer `seq` of this connection sealed under its key."""
    from cryptography.exceptions import InvalidTag

    view = memoryview(data)
    if len(view) < SEAL_OVERHEAD:
        raise ValueError(f"sealed transfer of {len(view)} bytes is shorter than its {SEAL_OVERHEAD}-byte "
                         f"overhead")
    (size,) = SEAL_HEAD.unpack_from(view)
    if not 16 <= size <= len(view) - SEAL_HEAD.size:
        raise ValueError(f"sealed transfer announces {size} bytes of ciphertext in {len(view)} bytes")
    try:
        return cipher.decrypt(_aead_nonce(seq), view[SEAL_HEAD.size:SEAL_HEAD.size + size], None)
    except InvalidTag:
        raise ValueError("transfer does not decrypt under this connection's key") from None


def tag_is_valid(expected: bytes, got: bytes | None) -> bool:
    return got is not None and hmac.compare_digest(expected, got)

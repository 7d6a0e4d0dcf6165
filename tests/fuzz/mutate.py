"""Byte-level mutators for seed-based fuzzing: bit flips, truncation, splicing, length-field edits."""

import random
import struct

INTERESTING = (0, 1, 0x7F, 0x80, 0xFF, 0x100, 0x7FFF, 0x8000, 0xFFFF, 0x7FFFFFFF, 0x80000000,
               0xFFFFFFFF, 2**63 - 1, 2**64 - 1)
FIELD_FORMATS = ("<B", "<H", "<I", "<Q", ">H", ">I")


def flip_bits(data: bytearray, rng: random.Random, _pool) -> bytearray:
    for _ in range(rng.randint(1, 4)):
        if data:
            i = rng.randrange(len(data))
            data[i] ^= 1 << rng.randrange(8)
    return data


def set_bytes(data: bytearray, rng: random.Random, _pool) -> bytearray:
    for _ in range(rng.randint(1, 4)):
        if data:
            data[rng.randrange(len(data))] = rng.choice((0x00, 0x01, 0x7F, 0x80, 0xFF, rng.randrange(256)))
    return data


def truncate(data: bytearray, rng: random.Random, _pool) -> bytearray:
    return data[: rng.randrange(len(data) + 1)]


def extend(data: bytearray, rng: random.Random, _pool) -> bytearray:
    tail = rng.choice((b"\x00", b"\xff", bytes([rng.randrange(256)]))) * rng.randint(1, 64)
    return data + rng.randbytes(rng.randint(1, 64)) if rng.random() < 0.5 else data + tail


def delete_span(data: bytearray, rng: random.Random, _pool) -> bytearray:
    if len(data) < 2:
        return data
    i = rng.randrange(len(data))
    del data[i:i + rng.randint(1, 16)]
    return data


def duplicate_span(data: bytearray, rng: random.Random, _pool) -> bytearray:
    if not data:
        return data
    i = rng.randrange(len(data))
    j = min(len(data), i + rng.randint(1, 64))
    k = rng.randrange(len(data) + 1)
    return data[:k] + data[i:j] + data[k:]


def splice(data: bytearray, rng: random.Random, pool) -> bytearray:
    other = rng.choice(pool)
    if not data or not other:
        return bytearray(other) + data
    cut = rng.randrange(len(data) + 1)
    start = rng.randrange(len(other))
    return data[:cut] + other[start:]


def edit_length_field(data: bytearray, rng: random.Random, _pool) -> bytearray:
    """Overwrite an integer field at a random offset with a boundary value or a near-miss of itself."""
    fmt = rng.choice(FIELD_FORMATS)
    size = struct.calcsize(fmt)
    if len(data) < size:
        return data
    off = rng.randrange(len(data) - size + 1)
    limit = 1 << (8 * size)
    if rng.random() < 0.5:
        value = rng.choice(INTERESTING) % limit
    else:
        (old,) = struct.unpack_from(fmt, data, off)
        value = (old + rng.choice((-2, -1, 1, 2, 64, -64, 1 << 16))) % limit
    struct.pack_into(fmt, data, off, value)
    return data


MUTATORS = (flip_bits, set_bytes, truncate, extend, delete_span, duplicate_span, splice, edit_length_field)


def mutate(seed: bytes, rng: random.Random, pool, max_len: int = 1 << 20) -> bytes:
    """One mutant of `seed`: 1-4 mutators chained; `pool` holds the seeds to splice with."""
    data = bytearray(seed)
    for _ in range(rng.randint(1, 4)):
        data = rng.choice(MUTATORS)(data, rng, pool)
    return bytes(data[:max_len])

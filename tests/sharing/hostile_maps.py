"""Hostile map messages for receive-path tests: tiny messages that announce huge maps."""

import zlib

import numpy as np

from coopd.sharing import codec_kernels, wire


def bomb(vehicle_id: int, version: int, shape=(1000, 1000, 100)) -> bytes:
    """A valid coopd map message (thesis encoding) of shape's cells, all unknown: a few dozen bytes
    of payload that decode to prod(shape) bytes."""
    n = int(np.prod(shape))
    out = np.empty(codec_kernels.EMIT_SLACK, dtype=np.int8)
    used = codec_kernels.emit_run(out, 0, np.int8(-1), np.int64(n))
    payload = out[:used].tobytes()
    header = wire.COOPD_HEADER.pack(
        wire.MSG_COOPD_MAP, wire.COOPD_MAP_VERSION, wire.COOPD_HEADER.size, vehicle_id, wire.MAP_3D,
        wire.ENCODINGS["thesis"], 0, *shape, 0, 0, 0, 0.1, 0.0, 0.0, 0.0, version, 0.0, len(payload),
        zlib.crc32(payload))
    return header + payload

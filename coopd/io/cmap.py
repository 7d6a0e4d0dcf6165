""".cmap files: exactly one serialized map message, the same bytes that go on the wire."""

import os
import stat

from coopd.grid import OccupancyGrid
from coopd.sharing.wire import DEFAULT_LIMITS, DecodeLimits, MapMeta, WireError, decode_map, encode_map

from .atomic import write_atomic

CMAP_SUFFIX = ".cmap"


def save_cmap(path, grid: OccupancyGrid, meta: MapMeta, encoding: str = "default") -> int:
    """Write grid + meta as a coopd map message, atomically; returns the bytes written."""
    data = encode_map(grid, meta, encoding)
    write_atomic(path, data)
    return len(data)


def read_cmap_bytes(path, limits: DecodeLimits = DEFAULT_LIMITS) -> bytes:
    """The raw message in a .cmap file, refusing files larger than limits.max_bytes unread."""
    with open(path, "rb") as f:
        st = os.fstat(f.fileno())
        if not stat.S_ISREG(st.st_mode):
            raise WireError(f"{path}: not a regular file")
        size = st.st_size
        if size > limits.max_bytes:
            raise WireError(f"{path}: {size} bytes exceeds the limit of {limits.max_bytes}")
        data = f.read(limits.max_bytes + 1)
    if len(data) > limits.max_bytes:
        raise WireError(f"{path}: file grew beyond the limit of {limits.max_bytes} bytes while read")
    return data


def load_cmap(path, limits: DecodeLimits = DEFAULT_LIMITS) -> tuple[OccupancyGrid, MapMeta]:
    """The grid and metadata stored in a .cmap file (thesis type 0 or coopd type 1)."""
    data = read_cmap_bytes(path, limits)
    try:
        return decode_map(data, limits)
    except WireError as e:
        raise WireError(f"{path}: {e}") from e

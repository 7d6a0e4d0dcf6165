"""OctoMap files: binary trees (.bt) written and read, full trees (.ot) read, by our own code so
neither needs an OctoMap install.

A .bt file is a text header followed by the tree in depth-first pre-order: every inner node
writes two bytes giving its 8 children two bits each (00 absent/unknown, 01 free leaf, 10
occupied leaf, 11 inner node; children 0-3 in the first byte, 4-7 in the second, child i at
bits 2i, 2i+1). OctoMap keys are 16 bits per axis; a voxel with key k spans [k - 32768,
k - 32767) · resolution. coopd cell key c (centred on c · resolution) is written as OctoMap
key c + 32768, so in OctoMap coordinates the map appears shifted by +resolution / 2 on each
axis: OctoMap cannot place voxel centres on multiples of the resolution. Eight sibling leaves
of one class are pruned into their parent, as OctoMap itself does before writing.

A .ot file (what `octomap_saver -f` writes; tree types OcTree, ColorOcTree, OcTreeStamped) holds
every node in pre-order: its value (float32 log-odds, then 3 colour bytes or a uint32 stamp for the
coloured and stamped types), then one byte saying which of its 8 children exist. Reading either
format maps OctoMap key k to coopd cell k - 32768 (the inverse of the export), a pruned leaf of
depth d to the 2^(16-d) cells per axis it stands for, and a .ot leaf's log-odds l to the cell value
round(100 / (1 + e^-l)). Files are hostile input: the header, the tree's shape and the size of the
grid it spans are checked before anything proportional to that size is allocated.
"""

import math
from dataclasses import dataclass

import numba as nb
import numpy as np

from coopd.grid import OccupancyGrid
from coopd.grid.cells import CELL_DTYPE, OCCUPIED_THRESHOLD, P_MAX, P_MIN, UNKNOWN
from coopd.kernel_cache import CACHE as KERNEL_CACHE

from .atomic import write_atomic
from .points import known_cells

TREE_DEPTH = 16
KEY_OFFSET = 1 << (TREE_DEPTH - 1)
FREE_LEAF, OCCUPIED_LEAF, INNER = 1, 2, 3
HEADER = "# Octomap OcTree binary file\n# written by coopd\nid OcTree\nsize {size}\nres {res}\ndata\n"
BT_MAGIC = b"# Octomap OcTree binary file"
OT_MAGIC = b"# Octomap OcTree file"
OT_NODE_EXTRA_BYTES = {"OcTree": 0, "ColorOcTree": 3, "OcTreeStamped": 4}
"""Bytes each tree type stores per node after its float32 log-odds (colour, or a uint32 stamp)."""
MAX_HEADER_BYTES = 4096


@nb.njit(nogil=True, cache=KERNEL_CACHE)
def morton_codes(keys):
    """48-bit codes whose 3-bit groups, most significant first, are OctoMap child indices."""
    n = keys.shape[0]
    out = np.empty(n, dtype=np.uint64)
    for i in range(n):
        code = np.uint64(0)
        for b in range(TREE_DEPTH):
            for axis in range(3):
                bit = (np.uint64(keys[i, axis]) >> np.uint64(b)) & np.uint64(1)
                code |= bit << np.uint64(3 * b + axis)
        out[i] = code
    return out


def _levels(codes: np.ndarray, kinds: np.ndarray):
    """Inner nodes per depth, bottom-up, with pruning: [(depth, codes, child descriptors)], leaves."""
    inner = []
    leaves = 0
    for depth in range(TREE_DEPTH - 1, -1, -1):
        parents = codes >> np.uint64(3)
        starts = np.flatnonzero(np.r_[True, parents[1:] != parents[:-1]])
        counts = np.diff(np.r_[starts, len(codes)])
        child = (codes & np.uint64(7)).astype(np.uint16)
        desc = np.bitwise_or.reduceat(kinds.astype(np.uint16) << (2 * child), starts)
        first_kind = kinds[starts]
        uniform = (np.minimum.reduceat(kinds, starts) == np.maximum.reduceat(kinds, starts))
        prunable = (counts == 8) & uniform & (first_kind != INNER)
        leaves += int(np.sum(np.where(prunable, 0, np.add.reduceat((kinds != INNER).astype(np.int64),
                                                                    starts))))
        keep = ~prunable
        inner.append((depth, parents[starts][keep], desc[keep].astype("<u2")))
        codes = parents[starts]
        kinds = np.where(prunable, first_kind, INNER).astype(np.uint8)
    return inner, leaves + int(np.sum(kinds != INNER))


def bt_bytes(grid: OccupancyGrid, threshold: int = OCCUPIED_THRESHOLD) -> bytes:
    """The .bt file of a grid: free and occupied cells as leaves, unknown cells absent."""
    keys, values = known_cells(grid)
    if len(keys) and (keys.min() < -KEY_OFFSET or keys.max() >= KEY_OFFSET):
        raise ValueError(f"cell keys outside ±{KEY_OFFSET} do not fit in an OctoMap tree")
    res = repr(float(grid.resolution))
    if len(keys) == 0:
        return HEADER.format(size=0, res=res).encode("ascii")
    codes = morton_codes(keys + KEY_OFFSET)
    order = np.argsort(codes, kind="stable")
    codes = codes[order]
    kinds = np.where(values[order] >= threshold, OCCUPIED_LEAF, FREE_LEAF).astype(np.uint8)
    inner, leaves = _levels(codes, kinds)
    padded = np.concatenate([c << np.uint64(3 * (TREE_DEPTH - d)) for d, c, _ in inner])
    depths = np.concatenate([np.full(len(c), d, np.int8) for d, c, _ in inner])
    desc = np.concatenate([x for _, _, x in inner])
    preorder = np.lexsort((depths, padded))
    size = len(desc) + leaves
    return HEADER.format(size=size, res=res).encode("ascii") + desc[preorder].tobytes()


def export_bt(grid: OccupancyGrid, path, threshold: int = OCCUPIED_THRESHOLD) -> int:
    """Write the grid as an OctoMap .bt file; returns its size in bytes."""
    data = bt_bytes(grid, threshold)
    write_atomic(path, data)
    return len(data)


# ------------------------------------------------------------------------------------------ reading
@dataclass(frozen=True)
class OctoMapHeader:
    """The text header of a .bt or .ot file."""

    binary: bool
    tree_type: str
    size: int
    """Nodes the header announces (inner nodes and leaves)."""
    resolution: float
    data_start: int


def is_octomap(data: bytes) -> bool:
    """Whether data starts like an OctoMap .bt or .ot file."""
    return data.startswith(BT_MAGIC) or data.startswith(OT_MAGIC)


def parse_header(data: bytes) -> OctoMapHeader:
    """The header of an OctoMap file; ValueError naming what is wrong."""
    binary = data.startswith(BT_MAGIC)
    if not binary and not data.startswith(OT_MAGIC):
        raise ValueError("not an OctoMap file (no '# Octomap OcTree' first line)")
    fields: dict[str, str] = {}
    pos = 0
    while True:
        end = data.find(b"\n", pos, MAX_HEADER_BYTES)
        if end < 0:
            raise ValueError(f"OctoMap header without a 'data' line in its first {MAX_HEADER_BYTES} bytes")
        line = data[pos:end].decode("ascii", "replace").strip()
        pos = end + 1
        if line == "data":
            break
        if line and not line.startswith("#"):
            key, _, value = line.partition(" ")
            fields[key] = value.strip()
    for key in ("id", "size", "res"):
        if key not in fields:
            raise ValueError(f"OctoMap header has no '{key}' line")
    tree_type = fields["id"]
    if binary and tree_type not in OT_NODE_EXTRA_BYTES:
        raise ValueError(f"OctoMap tree type {tree_type!r} is not an occupancy tree")
    if not binary and tree_type not in OT_NODE_EXTRA_BYTES:
        raise ValueError(f"OctoMap tree type {tree_type!r} is not supported (OcTree, ColorOcTree, "
                         f"OcTreeStamped)")
    try:
        size, res = int(fields["size"]), float(fields["res"])
    except ValueError:
        raise ValueError(f"OctoMap header: size {fields['size']!r} / res {fields['res']!r} are not "
                         f"numbers") from None
    if size < 0 or not (math.isfinite(res) and 1e-4 <= res <= 100.0):
        raise ValueError(f"OctoMap header: size {size} or resolution {res} m out of range")
    return OctoMapHeader(binary, tree_type, size, res, pos)


ERR_TRUNCATED, ERR_TOO_DEEP = 1, 2


@nb.njit(nogil=True, cache=KERNEL_CACHE)
def _f32(data, pos, scratch):
    """The little-endian float32 at data[pos]."""
    scratch[0] = (np.uint32(data[pos]) | (np.uint32(data[pos + 1]) << np.uint32(8))
                  | (np.uint32(data[pos + 2]) << np.uint32(16)) | (np.uint32(data[pos + 3]) << np.uint32(24)))
    return scratch.view(np.float32)[0]


@nb.njit(nogil=True, cache=KERNEL_CACHE)
def _leaf(leaves, n, x0, y0, z0, size, value):
    leaves[n, 0] = x0
    leaves[n, 1] = y0
    leaves[n, 2] = z0
    leaves[n, 3] = size
    leaves[n, 4] = value


@nb.njit(nogil=True, cache=KERNEL_CACHE)
def _walk(data, pos, binary, extra, leaves, fill):
    """Pre-order walk of the tree in data[pos:]: (nodes, end, leaf count, error). With fill, leaves
    rows get (x0, y0, z0, size in cells, value): keys of the leaf's lowest corner, and for .bt 1 free
    / 2 occupied, for .ot the log-odds. Iterative: the stack never holds more than the tree depth."""
    node_bytes = 5 + extra
    stack = np.zeros((TREE_DEPTH + 1, 6), dtype=np.int64)  # x0, y0, z0, depth, children, next child
    scratch = np.zeros(1, dtype=np.uint32)
    nodes = 0
    n_leaves = 0
    # the root
    if binary:
        if pos + 2 > data.shape[0]:
            return nodes, pos, n_leaves, ERR_TRUNCATED
        children = np.int64(data[pos]) | (np.int64(data[pos + 1]) << 8)
        pos += 2
    else:
        if pos + node_bytes > data.shape[0]:
            return nodes, pos, n_leaves, ERR_TRUNCATED
        children = np.int64(data[pos + node_bytes - 1])
        if children == 0:  # the root is the only leaf
            if fill:
                _leaf(leaves, 0, 0, 0, 0, 1 << TREE_DEPTH, _f32(data, pos, scratch))
            return 1, pos + node_bytes, 1, 0
        pos += node_bytes
    nodes += 1
    top = 0
    stack[0, 3] = 0
    stack[0, 4] = children
    stack[0, 5] = 0
    while top >= 0:
        i = stack[top, 5]
        if i == 8:
            top -= 1
            continue
        stack[top, 5] = i + 1
        depth = stack[top, 3] + 1
        half = np.int64(1) << (TREE_DEPTH - depth)
        x0 = stack[top, 0] + (i & 1) * half
        y0 = stack[top, 1] + ((i >> 1) & 1) * half
        z0 = stack[top, 2] + ((i >> 2) & 1) * half
        if binary:
            code = (stack[top, 4] >> (2 * i)) & 3
            if code == 0:
                continue
            nodes += 1
            if code < 3:
                if fill:
                    _leaf(leaves, n_leaves, x0, y0, z0, half, code)
                n_leaves += 1
                continue
            if depth == TREE_DEPTH:
                return nodes, pos, n_leaves, ERR_TOO_DEEP
            if pos + 2 > data.shape[0]:
                return nodes, pos, n_leaves, ERR_TRUNCATED
            children = np.int64(data[pos]) | (np.int64(data[pos + 1]) << 8)
            pos += 2
        else:
            if not (stack[top, 4] >> i) & 1:
                continue
            if pos + node_bytes > data.shape[0]:
                return nodes, pos, n_leaves, ERR_TRUNCATED
            nodes += 1
            children = np.int64(data[pos + node_bytes - 1])
            if children == 0:
                if fill:
                    _leaf(leaves, n_leaves, x0, y0, z0, half, _f32(data, pos, scratch))
                n_leaves += 1
                pos += node_bytes
                continue
            if depth == TREE_DEPTH:
                return nodes, pos, n_leaves, ERR_TOO_DEEP
            pos += node_bytes
        top += 1
        stack[top, 0] = x0
        stack[top, 1] = y0
        stack[top, 2] = z0
        stack[top, 3] = depth
        stack[top, 4] = children
        stack[top, 5] = 0
    return nodes, pos, n_leaves, 0


@nb.njit(nogil=True, cache=KERNEL_CACHE)
def _fill(cells, lo, leaves, values):
    """Set each leaf's box of cells (keys relative to lo) to its value."""
    for n in range(leaves.shape[0]):
        x0 = int(leaves[n, 0]) - lo[0]
        y0 = int(leaves[n, 1]) - lo[1]
        z0 = int(leaves[n, 2]) - lo[2]
        size = int(leaves[n, 3])
        for x in range(x0, x0 + size):
            for y in range(y0, y0 + size):
                for z in range(z0, z0 + size):
                    cells[x, y, z] = values[n]


def read_octomap(data: bytes, max_cells: int) -> OccupancyGrid:
    """The grid an OctoMap .bt or .ot file describes (module docstring); ValueError, before any
    allocation proportional to it, when the file is malformed or spans more than max_cells cells."""
    header = parse_header(data)
    buf = np.frombuffer(data, dtype=np.uint8)
    extra = OT_NODE_EXTRA_BYTES[header.tree_type]
    if header.size == 0:
        return OccupancyGrid.empty((1, 1, 1), header.resolution)
    nodes, end, n_leaves, err = _walk(buf, header.data_start, header.binary, extra,
                                      np.zeros((0, 5)), False)
    if err == ERR_TRUNCATED:
        raise ValueError(f"OctoMap tree truncated after {nodes} nodes ({len(data)} bytes)")
    if err == ERR_TOO_DEEP:
        raise ValueError(f"OctoMap tree deeper than {TREE_DEPTH} levels")
    if nodes != header.size:
        raise ValueError(f"OctoMap header announces {header.size} nodes, the tree holds {nodes}")
    if end != len(data):
        raise ValueError(f"{len(data) - end} bytes after the OctoMap tree")
    leaves = np.zeros((n_leaves, 5))
    _walk(buf, header.data_start, header.binary, extra, leaves, True)
    corner = leaves[:, :3].astype(np.int64)
    size = leaves[:, 3].astype(np.int64)
    lo = corner.min(axis=0)
    hi = (corner + size[:, None]).max(axis=0)
    shape = hi - lo
    if int(np.prod(shape)) > max_cells:
        raise ValueError(f"OctoMap tree spans {' x '.join(map(str, shape))} cells, more than the limit of "
                         f"{max_cells}")
    if header.binary:
        values = np.where(leaves[:, 4] == OCCUPIED_LEAF, P_MAX, P_MIN).astype(CELL_DTYPE)
    else:
        if not np.isfinite(leaves[:, 4]).all():
            raise ValueError("OctoMap tree holds a leaf whose log-odds is not a finite number")
        logodds = np.clip(leaves[:, 4], -50.0, 50.0)
        values = np.rint(P_MAX / (1.0 + np.exp(-logodds))).astype(CELL_DTYPE)
    cells = np.full(tuple(int(v) for v in shape), UNKNOWN, dtype=CELL_DTYPE)
    _fill(cells, lo, leaves, values)
    return OccupancyGrid(cells, header.resolution, lo - KEY_OFFSET)

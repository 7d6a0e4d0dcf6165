"""OctoMap binary trees (.bt), written by our own code so exports need no OctoMap install.

A .bt file is a text header followed by the tree in depth-first pre-order: every inner node
writes two bytes giving its 8 children two bits each (00 absent/unknown, 01 free leaf, 10
occupied leaf, 11 inner node; children 0-3 in the first byte, 4-7 in the second, child i at
bits 2i, 2i+1). OctoMap keys are 16 bits per axis; a voxel with key k spans [k - 32768,
k - 32767) · resolution. coopd cell key c (centred on c · resolution) is written as OctoMap
key c + 32768, so in OctoMap coordinates the map appears shifted by +resolution / 2 on each
axis: OctoMap cannot place voxel centres on multiples of the resolution. Eight sibling leaves
of one class are pruned into their parent, as OctoMap itself does before writing.
"""

import numba as nb
import numpy as np

from coopd.grid import OccupancyGrid
from coopd.grid.cells import OCCUPIED_THRESHOLD
from coopd.kernel_cache import CACHE as KERNEL_CACHE

from .atomic import write_atomic
from .points import known_cells

TREE_DEPTH = 16
KEY_OFFSET = 1 << (TREE_DEPTH - 1)
FREE_LEAF, OCCUPIED_LEAF, INNER = 1, 2, 3
HEADER = "# Octomap OcTree binary file\n# written by coopd\nid OcTree\nsize {size}\nres {res}\ndata\n"


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

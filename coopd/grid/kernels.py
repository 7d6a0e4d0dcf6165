"""numba kernels for whole-grid operations: bounding box, fusion, resampling under a rigid transform."""

import numba as nb
import numpy as np

from coopd.kernel_cache import CACHE as KERNEL_CACHE

from .cells import INACCESSIBLE, P_MIN, UNKNOWN

_JIT = {"nogil": True, "cache": KERNEL_CACHE, "boundscheck": False}


@nb.njit(**_JIT)
def known_bounds(cells):
    """Inclusive (lo, hi) array coordinates of the known cells; lo > hi when there are none."""
    mx, my, mz = cells.shape
    lo = np.array([mx, my, mz], dtype=np.int64)
    hi = np.array([-1, -1, -1], dtype=np.int64)
    for x in range(mx):
        for y in range(my):
            row = cells[x, y]
            first = -1
            last = -1
            for z in range(mz):
                if row[z] != UNKNOWN:
                    if first < 0:
                        first = z
                    last = z
            if first >= 0:
                if x < lo[0]:
                    lo[0] = x
                if x > hi[0]:
                    hi[0] = x
                if y < lo[1]:
                    lo[1] = y
                if y > hi[1]:
                    hi[1] = y
                if first < lo[2]:
                    lo[2] = first
                if last > hi[2]:
                    hi[2] = last
    return lo, hi


@nb.njit(inline="always")
def fuse_cell(a, b, threshold):
    """Table 3 of the thesis on one pair of cells; see coopd.grid.fusion for the rule in words."""
    if a == UNKNOWN:
        return b
    if b == UNKNOWN:
        return a
    if a == INACCESSIBLE:
        return b
    if b == INACCESSIBLE:
        return a
    if a >= threshold or b >= threshold:
        return a if a > b else b
    return a if a < b else b


@nb.njit(**_JIT)
def fuse_flat(dst, src, threshold):
    """dst[i] = fuse(dst[i], src[i]) for same-shaped 1D views."""
    for i in range(dst.shape[0]):
        dst[i] = fuse_cell(dst[i], src[i], threshold)


@nb.njit(**_JIT)
def fuse_block(dst, src, threshold):
    """dst = fuse(dst, src) cell by cell for same-shaped 3D views (slices allowed)."""
    mx, my, mz = dst.shape
    for x in range(mx):
        for y in range(my):
            for z in range(mz):
                dst[x, y, z] = fuse_cell(dst[x, y, z], src[x, y, z], threshold)


@nb.njit(**_JIT)
def resample_into(dst, dst_offset, src, src_offset, inv_rot, inv_trans, fuse, threshold):
    """Fill dst by inverse mapping: each dst cell centre is carried into src (key space, cells)
    by p_src = inv_rot @ k_dst + inv_trans and takes the nearest src cell. Cells that map outside
    src or onto unknown are left as they are. With fuse, values combine by Table 3; else they
    overwrite. Returns the number of dst cells written."""
    mx, my, mz = dst.shape
    sx, sy, sz = src.shape
    written = 0
    r00, r01, r02 = inv_rot[0, 0], inv_rot[0, 1], inv_rot[0, 2]
    r10, r11, r12 = inv_rot[1, 0], inv_rot[1, 1], inv_rot[1, 2]
    r20, r21, r22 = inv_rot[2, 0], inv_rot[2, 1], inv_rot[2, 2]
    for x in range(mx):
        kx = x + dst_offset[0]
        for y in range(my):
            ky = y + dst_offset[1]
            bx = r00 * kx + r01 * ky + inv_trans[0] - src_offset[0]
            by = r10 * kx + r11 * ky + inv_trans[1] - src_offset[1]
            bz = r20 * kx + r21 * ky + inv_trans[2] - src_offset[2]
            for z in range(mz):
                kz = z + dst_offset[2]
                ux = int(np.floor(bx + r02 * kz + 0.5))
                if ux < 0 or ux >= sx:
                    continue
                uy = int(np.floor(by + r12 * kz + 0.5))
                if uy < 0 or uy >= sy:
                    continue
                uz = int(np.floor(bz + r22 * kz + 0.5))
                if uz < 0 or uz >= sz:
                    continue
                v = src[ux, uy, uz]
                if v == UNKNOWN:
                    continue
                if fuse:
                    dst[x, y, z] = fuse_cell(dst[x, y, z], v, threshold)
                else:
                    dst[x, y, z] = v
                written += 1
    return written


@nb.njit(**_JIT)
def count_classes(flat, threshold):
    """(unknown, inaccessible, free, occupied) counts of a 1D cell view."""
    unknown = 0
    inaccessible = 0
    free = 0
    occupied = 0
    for i in range(flat.shape[0]):
        v = flat[i]
        if v == UNKNOWN:
            unknown += 1
        elif v == INACCESSIBLE:
            inaccessible += 1
        elif v >= threshold:
            occupied += 1
        elif v >= P_MIN:
            free += 1
    return unknown, inaccessible, free, occupied


@nb.njit(**_JIT)
def free_side(cells, threshold, x, y, z):
    """Unit direction from an occupied cell towards its known-free neighbours (26), or zeros when the
    free cells around it do not point one way (none, or all round): the side a map saw its surface
    from."""
    mx, my, mz = cells.shape
    n = np.zeros(3)
    for dx in range(-1, 2):
        for dy in range(-1, 2):
            for dz in range(-1, 2):
                a, b, c = x + dx, y + dy, z + dz
                if (dx == 0 and dy == 0 and dz == 0) or a < 0 or b < 0 or c < 0 or a >= mx or b >= my \
                        or c >= mz:
                    continue
                v = cells[a, b, c]
                if 0 <= v < threshold:
                    inv = 1.0 / np.sqrt(dx * dx + dy * dy + dz * dz)
                    n[0] += dx * inv
                    n[1] += dy * inv
                    n[2] += dz * inv
    length = np.sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2])
    if length < 1.0:
        return np.zeros(3)
    return n / length

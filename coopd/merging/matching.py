"""Correspondences (§8.6): brute-force Hamming distances in bounded chunks of keypoints."""

import numba as nb
import numpy as np

from coopd.kernel_cache import CACHE as KERNEL_CACHE

from .params import MergeParams

_JIT = {"nogil": True, "cache": KERNEL_CACHE}


@nb.njit(inline="always")
def _popcount(v):
    v = v - ((v >> np.uint64(1)) & np.uint64(0x5555555555555555))
    v = (v & np.uint64(0x3333333333333333)) + ((v >> np.uint64(2)) & np.uint64(0x3333333333333333))
    v = (v + (v >> np.uint64(4))) & np.uint64(0x0F0F0F0F0F0F0F0F)
    return int((v * np.uint64(0x0101010101010101)) >> np.uint64(56))


@nb.njit(**_JIT)
def hamming_block(da, db):
    """(len(db), len(da)) Hamming distances between two descriptor blocks."""
    out = np.empty((db.shape[0], da.shape[0]), dtype=np.int32)
    for i in range(db.shape[0]):
        for j in range(da.shape[0]):
            acc = 0
            for w in range(da.shape[1]):
                acc += _popcount(da[j, w] ^ db[i, w])
            out[i, j] = acc
    return out


def match(da: np.ndarray, db: np.ndarray, params: MergeParams):
    """(index in a, index in b, distance) of accepted pairs: all within CC_d, or each b's k nearest."""
    ia, ib, dd = [], [], []
    if len(da) == 0 or len(db) == 0:
        return np.empty(0, np.int64), np.empty(0, np.int64), np.empty(0, np.int32)
    k = params.match_best_k
    for start in range(0, len(db), params.match_chunk):
        d = hamming_block(da, db[start:start + params.match_chunk])
        rows = np.arange(d.shape[0])
        if k > 0:
            kk = min(k, d.shape[1])
            nearest = np.argpartition(d, kk - 1, axis=1)[:, :kk]
            r = np.repeat(rows, kk)
            c = nearest.reshape(-1)
            dist = d[r, c]
            ok = dist <= params.match_max_distance
            r, c, dist = r[ok], c[ok], dist[ok]
        else:
            r, c = np.nonzero(d <= params.match_max_distance)
            dist = d[r, c]
        ia.append(c.astype(np.int64))
        ib.append((r + start).astype(np.int64))
        dd.append(dist.astype(np.int32))
    return np.concatenate(ia), np.concatenate(ib), np.concatenate(dd)

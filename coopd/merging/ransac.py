"""Correspondence filter (§8.7): RANSAC over minimal samples, keeping several distinct hypotheses.

Models: 'homography' (Algorithm 5: 5 correspondences, the 4x4 homography as the null vector of their
linear system), 'rigid' (3-point Kabsch) and 'yaw' (2 points, yaw + translation, for gravity-aligned
maps). Rigid and yaw samples whose inter-point distances disagree are skipped before estimation (a
rigid motion keeps them).
"""

from dataclasses import dataclass

import numba as nb
import numpy as np

from coopd.kernel_cache import CACHE as KERNEL_CACHE

from ..geometry import rotation_angle_deg
from .mtm import estimate, kabsch, kabsch_yaw
from .params import MergeParams

_JIT = {"nogil": True, "cache": KERNEL_CACHE}
MODELS = {"homography": 0, "rigid": 1, "yaw": 2}
SAMPLE = {0: 5, 1: 3, 2: 2}


@dataclass(frozen=True)
class Hypothesis:
    """A candidate transform b -> a (metres) and the correspondences that support it."""

    transform: np.ndarray
    inliers: np.ndarray
    """Boolean mask over the correspondences."""

    @property
    def inlier_count(self) -> int:
        return int(self.inliers.sum())


@nb.njit(**_JIT)
def homography_system(pb, pa):
    """The 3n x 16 linear system P h = 0 of eq. 22: three rows per correspondence pa ~ H pb, with h
    the 4x4 H row by row."""
    n = pb.shape[0]
    p = np.zeros((3 * n, 16))
    for i in range(n):
        x = np.array([pb[i, 0], pb[i, 1], pb[i, 2], 1.0])
        for r in range(3):
            row = 3 * i + r
            for c in range(4):
                p[row, 4 * r + c] = -x[c]
                p[row, 12 + c] = x[c] * pa[i, r]
    return p


@nb.njit(**_JIT)
def homography(pb, pa):
    """4x4 H with pa ~ H pb from a 5-point sample: the null vector of its 15 x 16 system (eq. 22),
    which the thesis takes as the SVD's last right singular vector. Gaussian elimination with full
    pivoting finds the same vector without LAPACK. A degenerate sample (rank below 15, such as four
    coplanar points) has no single null vector and gives all zeros, which no correspondence fits."""
    p = homography_system(pb[:5], pa[:5])
    col = np.arange(16)
    scale = np.abs(p).max()
    for k in range(15):
        prow, pcol, best = k, k, 0.0
        for i in range(k, 15):
            for j in range(k, 16):
                if abs(p[i, j]) > best:
                    prow, pcol, best = i, j, abs(p[i, j])
        if not best > 1e-12 * scale:
            return np.zeros((4, 4))
        for j in range(16):
            p[k, j], p[prow, j] = p[prow, j], p[k, j]
        for i in range(15):
            p[i, k], p[i, pcol] = p[i, pcol], p[i, k]
        col[k], col[pcol] = col[pcol], col[k]
        for i in range(k + 1, 15):
            f = p[i, k] / p[k, k]
            if f != 0.0:
                for j in range(k, 16):
                    p[i, j] -= f * p[k, j]
    sol = np.zeros(16)
    sol[15] = 1.0  # the column left without a pivot is the free unknown
    for k in range(14, -1, -1):
        acc = 0.0
        for j in range(k + 1, 16):
            acc += p[k, j] * sol[j]
        sol[k] = -acc / p[k, k]
    h = np.empty(16)
    for j in range(16):
        h[col[j]] = sol[j]
    h = h.reshape(4, 4) / np.sqrt(np.sum(h * h))  # unit length, as the singular vector
    if abs(h[3, 3]) > 1e-12:
        h /= h[3, 3]
    return h


@nb.njit(**_JIT)
def residuals(t, pb, pa, projective):
    """|pa - T pb| per correspondence (projective divides by the fourth coordinate)."""
    n = pb.shape[0]
    out = np.empty(n)
    for i in range(n):
        x = t[0, 0] * pb[i, 0] + t[0, 1] * pb[i, 1] + t[0, 2] * pb[i, 2] + t[0, 3]
        y = t[1, 0] * pb[i, 0] + t[1, 1] * pb[i, 1] + t[1, 2] * pb[i, 2] + t[1, 3]
        z = t[2, 0] * pb[i, 0] + t[2, 1] * pb[i, 1] + t[2, 2] * pb[i, 2] + t[2, 3]
        if projective:
            w = t[3, 0] * pb[i, 0] + t[3, 1] * pb[i, 1] + t[3, 2] * pb[i, 2] + t[3, 3]
            if abs(w) < 1e-12:
                out[i] = np.inf
                continue
            x, y, z = x / w, y / w, z / w
        out[i] = np.sqrt((x - pa[i, 0]) ** 2 + (y - pa[i, 1]) ** 2 + (z - pa[i, 2]) ** 2)
    return out


@nb.njit(**_JIT)
def _consistent(pb, pa, idx, tol):
    """A rigid motion keeps distances: every pair of the sample must agree within 2 tol."""
    for i in range(idx.shape[0]):
        for j in range(i + 1, idx.shape[0]):
            db = np.sqrt(np.sum((pb[idx[i]] - pb[idx[j]]) ** 2))
            da = np.sqrt(np.sum((pa[idx[i]] - pa[idx[j]]) ** 2))
            if abs(db - da) > 2 * tol or db < 2 * tol:
                return False
    return True


@nb.njit(**_JIT)
def _sample(n, k):
    """k distinct indices of n by rejection: O(k^2), where np.random.choice without replacement
    permutes all n (most of RANSAC's time on thousands of correspondences)."""
    idx = np.empty(k, dtype=np.int64)
    i = 0
    while i < k:
        v = np.random.randint(0, n)
        for j in range(i):
            if idx[j] == v:
                break
        else:
            idx[i] = v
            i += 1
    return idx


@nb.njit(**_JIT)
def ransac(pb, pa, model, iterations, tol, seed):
    """All sampled hypotheses (iterations, 4, 4) with their inlier counts (-1 for skipped samples)."""
    np.random.seed(seed)
    n = pb.shape[0]
    k = 5 if model == 0 else (3 if model == 1 else 2)
    hyps = np.zeros((iterations, 4, 4))
    counts = np.full(iterations, -1, dtype=np.int64)
    if n < k:
        return hyps, counts
    for it in range(iterations):
        idx = _sample(n, k)
        if model != 0 and not _consistent(pb, pa, idx, tol):
            continue
        sb = np.empty((k, 3))
        sa = np.empty((k, 3))
        for q in range(k):
            sb[q] = pb[idx[q]]
            sa[q] = pa[idx[q]]
        if model == 0:
            t = homography(sb, sa)
        elif model == 1:
            t = kabsch(sb, sa)
        else:
            t = kabsch_yaw(sb, sa)
        res = residuals(t, pb, pa, model == 0)
        hyps[it] = t
        counts[it] = np.sum(res <= tol)
    return hyps, counts


def _distinct(t: np.ndarray, kept: list, min_angle_deg: float, min_shift_m: float) -> bool:
    for h in kept:
        if (rotation_angle_deg(h.transform[:3, :3].T @ t[:3, :3]) < min_angle_deg
                and np.linalg.norm(h.transform[:3, 3] - t[:3, 3]) < min_shift_m):
            return False
    return True


def _polish(pb: np.ndarray, pa: np.ndarray, inl: np.ndarray, tol_m: float, yaw_only: bool, rounds: int = 5):
    """MTM (Kabsch) on the inliers, the inliers re-selected by that rigid fit, until they settle."""
    t = estimate(pb[inl], pa[inl], yaw_only)
    for _ in range(rounds):
        again = residuals(t, pb, pa, False) <= tol_m
        if again.sum() < 3 or np.array_equal(again, inl):
            break
        inl = again
        t = estimate(pb[inl], pa[inl], yaw_only)
    return t, residuals(t, pb, pa, False) <= tol_m


def filter_correspondences(pb: np.ndarray, pa: np.ndarray, tol_m: float, params: MergeParams,
                           min_angle_deg: float = 10.0, min_shift_m: float = 1.0) -> list[Hypothesis]:
    """Up to params.hypotheses distinct rigid hypotheses b -> a, best supported first.

    The winning samples' inliers are re-estimated by Kabsch (the MTM of §8.8) and re-selected by that
    rigid fit. A hypothesis needs ransac_min_consensus correspondences beyond its minimal sample, counted
    under the rigid fit: a 5-point homography fits any 5 correspondences exactly (15 DoF), so the
    homography's own inlier count can never refuse anything.
    """
    model = MODELS[params.ransac_model]
    pb = np.ascontiguousarray(pb, dtype=np.float64)
    pa = np.ascontiguousarray(pa, dtype=np.float64)
    hyps, counts = ransac(pb, pa, model, params.ransac_iterations, float(tol_m), params.ransac_seed)
    kept: list[Hypothesis] = []
    yaw_only = params.gravity_aligned or model == 2
    need = max(3, SAMPLE[model] + params.ransac_min_consensus)
    for i in np.argsort(-counts, kind="stable"):
        if counts[i] < need or len(kept) >= params.hypotheses:
            break
        inl = residuals(hyps[i], pb, pa, model == 0) <= tol_m
        t, inl = _polish(pb, pa, inl, tol_m, yaw_only)
        if inl.sum() >= need and _distinct(t, kept, min_angle_deg, min_shift_m):
            kept.append(Hypothesis(t, inl))
    return kept

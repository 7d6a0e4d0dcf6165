"""Steered BRIEF 3D (§8.5, Algorithm 4): binary tests on a seeded 3D sample turned by the keypoint's
orientation, packed into uint64 words (256 tests -> 4 words).

The sample is rotated as column vectors, p = R(alpha, beta, gamma) s, so that a map turned by a yaw
turns the sample with it (Algorithm 4 writes S * R with row vectors; read literally that would turn
it the other way). `descriptor_steering` chooses the rotation: the yaw gamma alone, or all three
angles.
"""

import numba as nb
import numpy as np

from coopd.kernel_cache import CACHE as KERNEL_CACHE

from ..geometry import euler_to_matrix
from .fast3d import _nh_mean
from .params import MergeParams

_JIT = {"nogil": True, "cache": KERNEL_CACHE}


def make_sample(tests: int, window: int, seed: int) -> np.ndarray:
    """makeSample3D: 2*tests points uniform in the cube of half-size window/2 around the origin."""
    rng = np.random.default_rng(seed)
    return rng.uniform(-window / 2.0, window / 2.0, size=(2 * tests, 3))


@nb.njit(**_JIT)
def _describe(img, keypoints, rotations, sample, nr, words):
    n = keypoints.shape[0]
    tests = sample.shape[0] // 2
    out = np.zeros((n, words), dtype=np.uint64)
    for p in range(n):
        r = rotations[p]
        kx, ky, kz = keypoints[p, 0], keypoints[p, 1], keypoints[p, 2]
        for j in range(tests):
            vals = np.empty(2)
            for q in range(2):
                s = sample[2 * j + q]
                px = r[0, 0] * s[0] + r[0, 1] * s[1] + r[0, 2] * s[2]
                py = r[1, 0] * s[0] + r[1, 1] * s[1] + r[1, 2] * s[2]
                pz = r[2, 0] * s[0] + r[2, 1] * s[1] + r[2, 2] * s[2]
                vals[q] = _nh_mean(img, kx + int(np.floor(px + 0.5)), ky + int(np.floor(py + 0.5)),
                                   kz + int(np.floor(pz + 0.5)), nr)
            if vals[0] <= vals[1]:
                out[p, j // 64] |= np.uint64(1) << np.uint64(j % 64)
    return out


def rotation_matrices(angles: np.ndarray, yaw_only: bool) -> np.ndarray:
    """(k, 3, 3) rotations of keypoint orientations; yaw_only ignores roll and pitch."""
    if yaw_only:
        c, s = np.cos(angles[:, 2]), np.sin(angles[:, 2])
        r = np.zeros((len(angles), 3, 3))
        r[:, 0, 0], r[:, 0, 1], r[:, 1, 0], r[:, 1, 1], r[:, 2, 2] = c, -s, s, c, 1.0
        return r
    return np.array([euler_to_matrix(*a) for a in angles]).reshape(-1, 3, 3)


def describe(img: np.ndarray, keypoints: np.ndarray, angles: np.ndarray, params: MergeParams) -> np.ndarray:
    """(k, ceil(ds/64)) uint64 descriptors of the keypoints."""
    sample = make_sample(params.descriptor_tests, params.descriptor_window, params.descriptor_seed)
    words = -(-params.descriptor_tests // 64)
    if params.descriptor_steering not in ("yaw", "euler"):
        raise ValueError(f"descriptor_steering must be 'yaw' or 'euler', not {params.descriptor_steering!r}")
    rots = rotation_matrices(angles, params.descriptor_steering == "yaw")
    return _describe(img, np.ascontiguousarray(keypoints, dtype=np.int64), rots, sample,
                     params.descriptor_neighbourhood, words)

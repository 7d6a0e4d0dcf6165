"""Merging's heaviest kernels on the largest whole-building map, each against a plain peer in the same run.

Input: the hospital exploration pair of `scripts/bench thesis` (firmware_sim/exploration.py, 435 x 417
x 34 cells per map). Per kernel, CPU seconds (process time, best of --repeat) of coopd's
implementation and of a reference doing the same work with standard building blocks, their ratio, and
how far the outputs differ:

- preprocess (§8.1): coopd's `preprocess` against scipy.ndimage line filters on the float32 intensity
  image (grey dilation, erosion, renormalised Gaussian) followed by block means;
- nearest occupied cell (ICP's query, asked once per ICP iteration): `OccupiedCells.nearest` against
  the query of a scipy cKDTree over the occupied cell centres (built once per map, its build time
  reported apart), for the refinement points of map B carried by the truth and moved by 0.1 m, at
  ICP's first (6 cells) and held (1.5 cells) radii;
- FAST 3D and ICP: coopd's time alone (no peer: the figures the thesis bench's stages add up);
- the 5-point homography of RANSAC (§8.7) and Kabsch (§8.8, ICP's fit), by Jacobi eigenvectors
  (merging/eigen.py, no LAPACK) against the same kernels with numba's np.linalg.svd (LAPACK through
  SciPy, as coopd had them), on random samples of a rigid motion with 2 cm of noise.

Usage: scripts/bench merge_stages [--repeat N] [--world NAME]. JSON in out/bench/merge_stages.json.
"""

import argparse
import json
import sys
import time
from pathlib import Path

import numba as nb
import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from coopd.geometry import apply, euler_to_matrix, invert, rigid  # noqa: E402
from coopd.io.atomic import write_atomic  # noqa: E402
from coopd.merging.fast3d import fast3d  # noqa: E402
from coopd.merging.mtm import kabsch  # noqa: E402
from coopd.merging.pair import _refine_points, prepare  # noqa: E402
from coopd.merging.params import thesis_params  # noqa: E402
from coopd.merging.preprocess import intensity, preprocess  # noqa: E402
from coopd.merging.ransac import homography, homography_system  # noqa: E402
from coopd.merging.refine import icp  # noqa: E402
from firmware_sim import exploration  # noqa: E402


def cpu_best(fn, repeat: int):
    """(result, best process-time seconds of `repeat` runs after one untimed run)."""
    result = fn()
    best = float("inf")
    for _ in range(repeat):
        t = time.process_time()
        result = fn()
        best = min(best, time.process_time() - t)
    return result, best


def reference_preprocess(cells: np.ndarray, params) -> np.ndarray:
    """§8.1 with scipy.ndimage: float32 line filters for the closing, correlate1d for the Gaussian
    (renormalised at the borders), then block means."""
    img = intensity(cells)
    size = 2 * params.dilate_radius + 1
    for axis in range(3):
        img = ndimage.maximum_filter1d(img, size, axis=axis, mode="nearest")
    size = 2 * params.erode_radius + 1
    for axis in range(3):
        img = ndimage.minimum_filter1d(img, size, axis=axis, mode="nearest")
    x = np.arange(-params.gaussian_radius, params.gaussian_radius + 1, dtype=np.float64)
    w = np.exp(-0.5 * (x / params.gaussian_sigma) ** 2)
    for axis in range(3):
        n = img.shape[axis]
        shape = [1, 1, 1]
        shape[axis] = n
        norm = ndimage.correlate1d(np.ones(n), w, mode="constant").reshape(shape).astype(np.float32)
        img = ndimage.correlate1d(img, w.astype(np.float32), axis=axis, mode="constant") / norm
    f = 2 * params.downsample_radius
    m = [s // f for s in img.shape]
    img = img[: m[0] * f, : m[1] * f, : m[2] * f]
    return img.reshape(m[0], f, m[1], f, m[2], f).mean(axis=(1, 3, 5))


@nb.njit(cache=False)
def svd_homography(pb, pa):
    """The 5-point homography by numba's np.linalg.svd of the 3n x 16 system (LAPACK)."""
    h = np.ascontiguousarray(np.linalg.svd(homography_system(pb, pa))[2][-1]).reshape(4, 4).copy()
    return h / h[3, 3]


@nb.njit(cache=False)
def svd_kabsch(src, dst):
    """Kabsch as coopd had it: the cross-covariance in loops, numba's np.linalg.svd (LAPACK) and the
    reflection fix."""
    cs = np.zeros(3)
    cd = np.zeros(3)
    for i in range(src.shape[0]):
        cs += src[i]
        cd += dst[i]
    cs /= src.shape[0]
    cd /= src.shape[0]
    h = np.zeros((3, 3))
    for i in range(src.shape[0]):
        for r in range(3):
            for c in range(3):
                h[r, c] += (src[i, r] - cs[r]) * (dst[i, c] - cd[c])
    u, _, vt = np.linalg.svd(h)
    v = vt.T.copy()
    r = v @ u.T
    if np.linalg.det(r) < 0:
        v[:, 2] *= -1.0
        r = v @ u.T
    t = np.eye(4)
    t[:3, :3] = r
    t[:3, 3] = cd - r @ cs
    return t


def small_fits(entry, repeat: int, count: int = 2000) -> None:
    """Homographies of 5-point samples and Kabsch fits of 200 points: ours against LAPACK's SVD."""
    rng = np.random.default_rng(0)
    t = rigid(euler_to_matrix(0.1, -0.05, 2.0), [3.0, -2.0, 0.4])
    for name, fn, peer_fn, n in (("homography (5 points)", homography, svd_homography, 5),
                                 ("kabsch (200 points)", kabsch, svd_kabsch, 200)):
        pbs = rng.uniform(-8, 8, (count, n, 3))
        pairs = list(zip(pbs, pbs @ t[:3, :3].T + t[:3, 3] + rng.normal(0, 0.02, pbs.shape), strict=True))
        ours_h, ours = cpu_best(lambda f=fn, ps=pairs: [f(pb, pa) for pb, pa in ps], repeat)
        peer_h, peer = cpu_best(lambda f=peer_fn, ps=pairs: [f(pb, pa) for pb, pa in ps], repeat)
        diff = max(float(np.abs(x - y).max() / np.abs(y).max()) for x, y in zip(ours_h, peer_h, strict=True))
        entry(f"{name} x {count}", ours, peer, max_relative_difference=diff)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--world", default="hospital")
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--out", type=Path, default=Path("out/bench/merge_stages.json"))
    args = ap.parse_args()
    params = thesis_params()
    a_map, b_map = exploration.world_explorations(args.world)
    a, b = a_map.grid, b_map.grid
    report = {"world": args.world, "shape": list(a.shape), "repeat": args.repeat, "kernels": {}}

    def entry(name, ours, peer=None, **extra):
        row = {"coopd_cpu_s": round(ours, 4)}
        if peer is not None:
            row.update(reference_cpu_s=round(peer, 4), speedup=round(peer / max(ours, 1e-9), 2))
        row.update(extra)
        report["kernels"][name] = row
        print(f"{name:34s} {json.dumps(row)}", file=sys.stderr)

    fi, ours = cpu_best(lambda: preprocess(a, params), args.repeat)
    ref, peer = cpu_best(lambda: reference_preprocess(a.cells, params), args.repeat)
    entry("preprocess (per map)", ours, peer, max_abs_difference=float(np.abs(fi.image - ref).max()))

    kp, ours = cpu_best(lambda: fast3d(fi.image, fi.known, params), args.repeat)
    entry("fast3d (per map)", ours, keypoints=len(kp), known_cells=int(fi.known.sum()))

    pa, pb = prepare(a, params, lazy=True), prepare(b, params, lazy=True)
    truth = invert(a_map.world_from_map) @ b_map.world_from_map
    source, normals = _refine_points(pb, params)
    moved = apply(truth, source) + np.array([0.1, 0.0, 0.0])
    centres = pa.summary.occupied_m
    tree, build = cpu_best(lambda: cKDTree(centres), args.repeat)
    report["kd_tree_build_cpu_s"] = round(build, 4)
    for cells in (6.0, 1.5):
        radius = cells * a.resolution
        (within, nearest), ours = cpu_best(lambda r=radius: pa.occupied.nearest(moved, r), args.repeat)
        (d_ref, _), peer = cpu_best(lambda r=radius: tree.query(moved, distance_upper_bound=r), args.repeat)
        d = np.linalg.norm(nearest[within] - moved[within], axis=1)
        same = bool(np.array_equal(within, np.isfinite(d_ref)) and np.allclose(d, d_ref[within], atol=1e-9))
        entry(f"nearest occupied, radius {cells:g} cells", ours, peer, points=len(moved),
              occupied_cells=len(centres), same_distances=same)
    start = truth.copy()
    start[:3, 3] += [0.3, -0.2, 0.0]
    sides = normals if params.refine_facing else None  # as the pipeline refines
    _, ours = cpu_best(lambda: icp(pa.occupied, source, start, params.refine_iterations, sides), args.repeat)
    entry("icp (one hypothesis, 0.36 m off)", ours, points=len(source))
    small_fits(entry, args.repeat)
    write_atomic(args.out, (json.dumps(report, indent=1) + "\n").encode())
    print(json.dumps(report, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())

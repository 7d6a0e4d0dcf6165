"""One map's features: preprocess, FAST 3D, filter, orient, describe (§8.1-8.5), timed per stage."""

import time
from dataclasses import dataclass, field

import numpy as np

from ..grid import OccupancyGrid
from .brief3d import describe
from .fast3d import fast3d
from .keypoint_filter import filter_keypoints
from .orientation import orientations
from .params import MergeParams
from .preprocess import preprocess


@dataclass(frozen=True)
class MapFeatures:
    """Keypoints (metres, map frame), their descriptors, orientations and the seconds each stage took."""

    points_m: np.ndarray
    descriptors: np.ndarray
    angles: np.ndarray
    cell_m: float
    detected: int
    timings: dict = field(default_factory=dict)


def extract(grid: OccupancyGrid, params: MergeParams) -> MapFeatures:
    """Run §8.1-8.5 on a grid."""
    tm = {}
    t0 = time.perf_counter()
    fi = preprocess(grid, params)
    tm["preprocess"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    kp = fast3d(fi.image, fi.known, params)
    tm["fast3d"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    fk, _ = filter_keypoints(fi.image, kp, params)
    tm["filter"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    ang = orientations(fi.image, fk, params)
    tm["orientation"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    desc = describe(fi.image, fk, ang, params)
    tm["describe"] = time.perf_counter() - t0
    return MapFeatures(fi.to_metres(fk), desc, ang, fi.cell_m, len(kp), tm)

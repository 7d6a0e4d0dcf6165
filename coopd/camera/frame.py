"""A validated depth frame, stamped in the flight controller's time base."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..mapping.sensor import Intrinsics


@dataclass(frozen=True)
class DepthFrame:
    """z16 depth (uint16 H x W, 0 = no return; metres = value * intrinsics.depth_scale) at FC time t_fc."""

    seq: int
    t_fc: float
    depth: np.ndarray
    intrinsics: Intrinsics
    min_m: float
    max_m: float
    received_local: float  # time.monotonic() when the last byte arrived

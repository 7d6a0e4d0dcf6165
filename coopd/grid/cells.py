"""Cell values of the occupancy grid (thesis §6.1, notes §2) and how they classify."""

import numpy as np

UNKNOWN = -1
"""Never observed."""
INACCESSIBLE = -2
"""Marked as not reachable; known, but neither free nor occupied."""
P_MIN = 0
"""Certainly free."""
P_MAX = 100
"""Certainly occupied."""
P_PRIOR = 50
"""What an unknown cell becomes just before its first update (notes §3)."""
OCCUPIED_THRESHOLD = 50
"""Default classification: occupied if p >= threshold, free if 0 <= p < threshold."""

CELL_DTYPE = np.int8


def is_valid_cells(values: np.ndarray) -> bool:
    """True when every value is a legal cell (-2, -1 or 0..100)."""
    if values.size == 0:
        return True
    return bool(values.min() >= INACCESSIBLE and values.max() <= P_MAX)


def occupied_mask(values: np.ndarray, threshold: int = OCCUPIED_THRESHOLD) -> np.ndarray:
    return values >= threshold


def free_mask(values: np.ndarray, threshold: int = OCCUPIED_THRESHOLD) -> np.ndarray:
    return (values >= P_MIN) & (values < threshold)


def known_mask(values: np.ndarray) -> np.ndarray:
    """Cells that carry information: anything but UNKNOWN (inaccessible counts as known)."""
    return values != UNKNOWN

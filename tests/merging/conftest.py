"""Shared fixtures of the merging tests: one small generated world and a few partial-map pairs."""

import numpy as np
import pytest

from firmware_sim.benchset import make_pair, make_world


@pytest.fixture(scope="session")
def world():
    return make_world(0)


@pytest.fixture(scope="session")
def near_pair(world):
    """Two maps with large overlap (explored boxes 3 m apart)."""
    return make_pair(world, 101, 3.0)


@pytest.fixture(scope="session")
def far_pair(world):
    """Two small maps 16 m apart: no overlap, must be rejected."""
    return make_pair(world, 905, 16.0, box_size_m=6.0)


def box_room(shape=(40, 40, 20), wall=2):
    """An int8 occupancy array: a closed box room (occupied shell, free inside)."""
    cells = np.full(shape, 80, dtype=np.int8)
    cells[wall:-wall, wall:-wall, wall:-wall] = 10
    return cells

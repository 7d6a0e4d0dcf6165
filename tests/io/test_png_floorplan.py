"""The PNG top view reads like a floor plan: floor and ceiling do not hide the rooms."""

import numpy as np

from coopd.grid import OccupancyGrid
from coopd.io.png import FREE, OCCUPIED, UNKNOWN, floor_and_ceiling_layers, top_classes


def room() -> OccupancyGrid:
    cells = np.full((30, 20, 25), 10, dtype=np.int8)      # free inside
    cells[:, :, 0] = 90                                    # floor
    cells[:, :, 24] = 90                                   # ceiling
    cells[15, :, :] = 95                                   # a wall across the room
    cells[5:8, 5:8, 1:8] = 80                              # a table
    cells[:, 18:, :] = -1                                  # a strip never seen
    return OccupancyGrid(cells, 0.1)


def test_floor_and_ceiling_are_found():
    assert set(floor_and_ceiling_layers(room().cells)) == {0, 1, 23, 24}


def test_top_view_shows_walls_and_furniture_not_the_floor():
    top = top_classes(room())
    assert top[2, 2] == FREE
    assert top[15, 3] == OCCUPIED and top[6, 6] == OCCUPIED
    assert top[2, 19] == UNKNOWN


def test_open_map_without_horizontal_surfaces_keeps_every_layer():
    cells = np.full((10, 10, 10), -1, dtype=np.int8)
    cells[4, 4, 3] = 90
    cells[2, 2, 2] = 10
    grid = OccupancyGrid(cells, 0.1)
    assert len(floor_and_ceiling_layers(cells)) == 0
    assert top_classes(grid)[4, 4] == OCCUPIED

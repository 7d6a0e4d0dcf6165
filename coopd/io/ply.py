"""PLY point cloud of the occupied cells (binary little-endian; opens in MeshLab, CloudCompare, Open3D)."""

import numpy as np

from coopd.grid import OccupancyGrid
from coopd.grid.cells import OCCUPIED_THRESHOLD

from .atomic import write_atomic
from .points import occupied_cells

VERTEX = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("occupancy", "u1")])


def ply_bytes(grid: OccupancyGrid, threshold: int = OCCUPIED_THRESHOLD) -> bytes:
    """One vertex per occupied cell: its centre in map-frame metres and its occupancy 0..100."""
    keys, values = occupied_cells(grid, threshold)
    vertices = np.empty(len(keys), dtype=VERTEX)
    centres = grid.centres_of(keys)
    vertices["x"], vertices["y"], vertices["z"] = centres[:, 0], centres[:, 1], centres[:, 2]
    vertices["occupancy"] = values
    header = ("ply\nformat binary_little_endian 1.0\n"
              f"comment coopd occupied cells (p >= {threshold}), resolution {grid.resolution} m, "
              "map frame ENU\n"
              f"element vertex {len(vertices)}\n"
              "property float x\nproperty float y\nproperty float z\n"
              "property uchar occupancy\nend_header\n")
    return header.encode("ascii") + vertices.tobytes()


def export_ply(grid: OccupancyGrid, path, threshold: int = OCCUPIED_THRESHOLD) -> int:
    """Write the occupied cells as a PLY point cloud; returns the number of points."""
    data = ply_bytes(grid, threshold)
    write_atomic(path, data)
    return (len(data) - data.index(b"end_header\n") - len(b"end_header\n")) // VERTEX.itemsize

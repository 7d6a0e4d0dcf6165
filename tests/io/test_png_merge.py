"""The merge PNG: both maps in A's frame, structure of A, of B and of both told apart."""

import numpy as np
from PIL import Image

from coopd.geometry import rigid
from coopd.grid import OccupancyGrid
from coopd.io.png import (
    BOTH,
    LEGEND_HEIGHT,
    MERGE_COLOURS,
    NEITHER,
    ONLY_A,
    ONLY_B,
    SEEN_FREE,
    export_png_merge,
    merge_classes,
)


def room(wall_x: int) -> OccupancyGrid:
    """A 2 m x 2 m room seen free, with a wall across it at x index wall_x."""
    cells = np.full((20, 20, 10), 10, dtype=np.int8)
    cells[wall_x, :, :] = 90
    return OccupancyGrid(cells, 0.1)


def test_classes_tell_a_b_and_both_over_both_extents():
    a = room(5)
    b = OccupancyGrid(room(5).cells, 0.1, offset=(10, 0, 0))  # its wall at x index 15 in a's frame
    b.cells[5, :10, :] = -1  # half of b's wall unseen
    classes = merge_classes(a, b)
    assert classes.shape == (30, 20)
    assert classes[5, 3] == ONLY_A and classes[15, 15] == ONLY_B
    assert classes[15, 3] == SEEN_FREE  # a saw free where b's wall went unseen
    assert classes[2, 2] == SEEN_FREE and classes[25, 2] == SEEN_FREE
    same = merge_classes(a, room(5))
    assert np.all(same[5] == BOTH) and not np.any(same == ONLY_A) and not np.any(same == NEITHER)


def test_png_of_a_merge_carries_b_by_the_transform(tmp_path):
    a, b = room(5), room(8)
    right = rigid(translation=[-0.3, 0.0, 0.0])  # b's wall onto a's
    export_png_merge(a, b, right, tmp_path / "right.png", "right")
    export_png_merge(a, b, np.eye(4), tmp_path / "wrong.png")
    both, only_a, only_b = (tuple(int(v) for v in MERGE_COLOURS[k]) for k in (BOTH, ONLY_A, ONLY_B))
    # the legend shows every colour; the map area decides how many pixels each gets
    pixels = {name: np.asarray(Image.open(tmp_path / f"{name}.png").convert("RGB"))[:-LEGEND_HEIGHT]
              for name in ("right", "wrong")}
    count = {name: {c: int(np.all(p == c, axis=-1).sum()) for c in (both, only_a, only_b)}
             for name, p in pixels.items()}
    assert count["right"][both] > 0 and count["right"][only_a] == 0 and count["right"][only_b] == 0
    assert count["wrong"][both] == 0 and count["wrong"][only_a] > 0 and count["wrong"][only_b] > 0
    assert Image.open(tmp_path / "right.png").info["Title"] == "right"

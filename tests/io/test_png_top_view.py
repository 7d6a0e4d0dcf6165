"""The floor-plan top view: scale bar, metre axes, origin, title and drones' tracks land on the
pixels the map's resolution and offset put them, in the layout and in the drawn PNG."""

import numpy as np
import pytest
from PIL import Image

from coopd.grid import OccupancyGrid
from coopd.io.png import (
    COLOURS,
    FREE,
    LABELS,
    OCCUPIED,
    ORIGIN_COLOUR,
    TRACK_COLOURS,
    export_png_top,
    map_title,
    scale_for,
)
from coopd.io.png_layout import TICK_SPACING_PX, metres_text, round_length, top_layout


def room() -> OccupancyGrid:
    """A 6 m x 4 m room at 0.1 m whose map origin is 2 m from its left wall, 1 m from its bottom."""
    cells = np.full((60, 40, 6), -1, np.int8)
    cells[1:59, 1:39, 1:5] = 0
    cells[0, :, :] = cells[59, :, :] = cells[:, 0, :] = cells[:, 39, :] = 100
    return OccupancyGrid(cells, 0.1, (-20, -10, -2))


@pytest.mark.parametrize("limit, expect", [(1.0, 1.0), (1.99, 1.0), (2.0, 2.0), (4.9, 2.0), (7.5, 5.0),
                                           (0.37, 0.2), (12.0, 10.0)])
def test_round_length(limit, expect):
    assert round_length(limit) == pytest.approx(expect)


def test_scale_bar_length_is_its_metres_over_resolution_times_pixel_scale():
    for shape, resolution in [((60, 40), 0.1), ((300, 80), 0.05), ((17, 9), 0.25), ((400, 400), 0.15)]:
        scale = scale_for(shape)
        layout = top_layout(shape, (0, 0), resolution, scale, "t", LABELS)
        x0, x1, _ = layout.scale_bar
        assert x1 - x0 == round(layout.scale_bar_m / resolution * scale)
        width_m = shape[0] * resolution
        assert layout.scale_bar_m <= width_m / 4 + 1e-9 or layout.scale_bar_m == pytest.approx(resolution)
        assert layout.scale_bar_m == round_length(layout.scale_bar_m)


def test_axes_ticks_sit_at_their_metres():
    grid = room()
    layout = top_layout(grid.shape[:2], grid.offset[:2], grid.resolution, 4, "t", LABELS)
    left, top, right, bottom = layout.map_box
    assert layout.x_ticks and layout.y_ticks
    for x, label in layout.x_ticks:
        # the map's left edge is at (-20 - 0.5) * 0.1 = -2.05 m; 40 pixels per metre at scale 4
        assert x == round(left + (float(label) + 2.05) * 40) and left <= x <= right
    for y, label in layout.y_ticks:
        assert y == round(bottom - (float(label) + 1.05) * 40) and top <= y <= bottom
    assert "0" in [label for _, label in layout.x_ticks] and "0" in [label for _, label in layout.y_ticks]
    steps = np.diff([float(label) for _, label in layout.x_ticks])
    assert np.allclose(steps, steps[0]) and steps[0] * 40 >= TICK_SPACING_PX


def test_origin_and_track_points_land_on_their_cells(tmp_path):
    grid = room()
    track = np.array([[0.0, 0.0], [1.0, 0.5], [2.5, -0.5], [np.nan, 1.0], [-1.5, 2.0]])
    layout = export_png_top(grid, tmp_path / "top.png", tracks={2: track})
    s = scale_for(grid.shape[:2])
    left, top, _, bottom = layout.map_box
    # key k is the cell centred at k * resolution: the origin is the centre of key (0, 0), i.e.
    # array cell (20, 10), whose pixel block starts at column left + 20 s, row bottom - 11 s
    assert layout.origin_px == pytest.approx((left + 20 * s + s / 2, bottom - 10 * s - s / 2))
    (drawn,) = layout.tracks
    assert drawn.vehicle_id == 2 and len(drawn.points_px) == 4  # the row that is not finite is left out
    for (x_m, y_m), (px, py) in zip(track[[0, 1, 2, 4]], drawn.points_px, strict=True):
        cell = (int(np.floor(x_m / 0.1 + 0.5)) + 20, int(np.floor(y_m / 0.1 + 0.5)) + 10)
        assert (int((px - left) // s), int((bottom - py) // s)) == cell
    image = Image.open(tmp_path / "top.png").convert("RGB")
    colour = TRACK_COLOURS[0]
    end = drawn.points_px[-1]
    assert image.getpixel((int(end[0]), int(end[1]))) == colour  # the final-position marker
    mid = np.mean(drawn.points_px[1:3], axis=0)
    assert image.getpixel((int(round(mid[0])), int(round(mid[1])))) == colour  # the polyline between points
    ox, oy = layout.origin_px
    assert image.getpixel((int(ox) + 5, int(oy))) == ORIGIN_COLOUR  # the origin cross


def test_title_and_notes_make_room_and_are_recorded(tmp_path):
    grid = room()
    plain = export_png_top(grid, tmp_path / "plain.png")
    title = map_title(grid.resolution, vehicle_id=3, stamp=1_700_000_000.0)
    assert title == "coopd map of vehicle 3, 2023-11-14 22:13:20 UTC, 0.1 m/cell"
    notes = ["drone 4: not merged into this map, track not drawn"]
    full = export_png_top(grid, tmp_path / "full.png", title=title, tracks={1: [[0, 0], [1, 1]]}, notes=notes)
    assert full.title == title and Image.open(tmp_path / "full.png").info["Title"] == title
    assert full.size[1] > plain.size[1]  # the note's line under the legend
    assert [label for *_, label in full.legend] == [*LABELS, "drone 1 track", *notes]
    assert full.swatches == len(LABELS) + 1
    image = Image.open(tmp_path / "full.png").convert("RGB")
    assert image.size == full.size
    title_band = np.asarray(image)[: full.map_box[1] - 2]
    assert (title_band.sum(axis=2) < 200).any()  # dark title text above the map
    s = full.scale
    assert image.getpixel((full.map_box[0] + 1, full.map_box[1] + 1)) == tuple(COLOURS[OCCUPIED])  # the wall
    assert image.getpixel((full.map_box[0] + 30 * s, full.map_box[1] + 5 * s)) == tuple(COLOURS[FREE])


def test_a_map_away_from_its_origin_has_no_origin_marker():
    layout = top_layout((10, 10), (50, 50), 0.1, 8, "t", LABELS)
    assert layout.origin_px is None


@pytest.mark.parametrize("value, text", [(0.0, "0"), (-0.0, "0"), (1.0, "1"), (0.5, "0.5"), (-2.25, "-2.25"),
                                         (10.0, "10")])
def test_metres_text(value, text):
    assert metres_text(value) == text


def test_a_track_leaving_the_map_stops_at_its_edge(tmp_path):
    grid = room()
    layout = export_png_top(grid, tmp_path / "top.png", tracks={1: [[0.0, 0.0], [0.0, 20.0]]})
    image = Image.open(tmp_path / "top.png").convert("RGB")
    column = int(layout.origin_px[0])
    top = layout.map_box[1]
    assert image.getpixel((column, top + 2)) == TRACK_COLOURS[0]  # inside the map, up to its edge
    assert image.getpixel((column, top - 1)) == (0, 0, 0)  # the map's frame line, not the track
    assert image.getpixel((column, top - 3)) == (255, 255, 255)  # nothing drawn above the map

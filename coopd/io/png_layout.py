"""Where everything goes on a top-view PNG, as plain numbers: the map, its metre axes, the scale
bar, the origin marker, the drones' tracks, the title and the legend. Pure (no Pillow) so tests
can check the geometry the drawing uses; coopd.io.png draws exactly what this lays out."""

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np

MARGIN_LEFT = 56
"""Room for the y axis' tick labels (metres, right-aligned against the map)."""
MARGIN_RIGHT = 24
TITLE_HEIGHT = 22
AXIS_HEIGHT = 18
"""Room under the map for the x axis' tick labels."""
SCALE_BAR_HEIGHT = 24
LEGEND_ROW = 18
TICK_SPACING_PX = 50
"""Axis ticks are a round number of metres apart, at least about this many pixels."""
SCALE_BAR_FRACTION = 0.25
"""The scale bar is the longest round length up to this fraction of the map's width."""
MIN_WIDTH = 360


def default_text_width(text: str) -> float:
    """Pixels a line of Pillow's default font takes, about (tests lay out without Pillow)."""
    return 6.0 * len(text)


def round_length(limit: float) -> float:
    """The largest 1, 2 or 5 times a power of ten that is at most `limit` (> 0)."""
    power = 10.0 ** math.floor(math.log10(limit))
    return max(m * power for m in (1.0, 2.0, 5.0) if m * power <= limit * (1 + 1e-9))


def metres_text(value: float) -> str:
    """A tick label: as few decimals as a round step needs (1, 0.5, 0.25 -> '1', '0.5', '0.25')."""
    text = f"{value:.3f}".rstrip("0").rstrip(".")
    return "0" if text in ("-0", "") else text


@dataclass(frozen=True)
class Track:
    """A drone's track on the image: its polyline and final position in pixels, its label."""

    vehicle_id: int
    points_px: list[tuple[float, float]]
    label: str
    label_px: tuple[float, float]


@dataclass(frozen=True)
class TopLayout:
    """Pixel positions of everything on a top view (x to the right, y down, (0, 0) top left)."""

    size: tuple[int, int]
    scale: int
    """Pixels per cell side."""
    resolution: float
    map_box: tuple[int, int, int, int]
    """left, top, right, bottom (exclusive) of the map's pixels."""
    lo_m: tuple[float, float]
    """Map-frame metres at the map's left and bottom edges."""
    title: str
    title_px: tuple[int, int]
    x_ticks: list[tuple[int, str]]
    """(pixel column, label in metres) along the bottom edge."""
    y_ticks: list[tuple[int, str]]
    """(pixel row, label in metres) along the left edge."""
    scale_bar: tuple[int, int, int]
    """left column, right column, row of the scale bar."""
    scale_bar_m: float
    origin_px: tuple[float, float] | None
    """Where the map frame's origin is, or None when the map does not reach it."""
    tracks: list[Track]
    legend: list[tuple[int, int, str]]
    """(x, y, label) of each legend entry; classes first, then tracks, then notes (no swatch)."""
    swatches: int
    """How many legend entries (the first ones) have a colour square."""

    def pixel(self, xy_m) -> tuple[float, float]:
        """Image pixel (column, row) of a map-frame point in metres; pixel centres at +0.5."""
        return map_pixel(self.map_box, self.lo_m, self.scale / self.resolution, xy_m)


def map_pixel(map_box, lo_m, per_m: float, xy_m) -> tuple[float, float]:
    """Image (column, row) of map-frame metres xy_m: x to the right from the map's left edge,
    y (north) up from its bottom edge."""
    return (map_box[0] + (float(xy_m[0]) - lo_m[0]) * per_m, map_box[3] - (float(xy_m[1]) - lo_m[1]) * per_m)


def tick_step(per_m: float) -> float:
    """The smallest 1, 2 or 5 times a power of ten metres that is at least TICK_SPACING_PX pixels."""
    raw = TICK_SPACING_PX / per_m
    power = 10.0 ** math.floor(math.log10(raw))
    return next(m * power for m in (1.0, 2.0, 5.0, 10.0) if m * power >= raw * (1 - 1e-9))


def _ticks(lo_m: float, hi_m: float, per_m: float, to_px: Callable[[float], float]) -> list[tuple[int, str]]:
    step = tick_step(per_m)
    first = math.ceil(lo_m / step - 1e-9)
    count = int(math.floor(hi_m / step + 1e-9)) - first + 1
    values = [(first + k) * step for k in range(max(count, 0))]
    return [(int(round(to_px(m))), metres_text(m)) for m in values]


def top_layout(shape_xy: tuple[int, int], offset_xy, resolution: float, scale: int, title: str,
               class_labels: Sequence[str], tracks: Mapping[int, np.ndarray] | None = None,
               notes: Sequence[str] = (),
               text_width: Callable[[str], float] = default_text_width) -> TopLayout:
    """Lay out a top view of a map of shape_xy cells whose first cell has keys offset_xy (a key
    k is the cell centred at k * resolution metres). `tracks` maps a vehicle id to its (N, 2)
    positions in metres in this map's frame (rows that are not finite are left out); `notes` are
    extra legend lines (say, drones whose track could not be drawn in this frame)."""
    width_px, height_px = int(shape_xy[0]) * scale, int(shape_xy[1]) * scale
    left, top = MARGIN_LEFT, TITLE_HEIGHT
    map_box = (left, top, left + width_px, top + height_px)
    lo_m = tuple((float(offset_xy[k]) - 0.5) * resolution for k in range(2))
    hi_m = tuple(lo_m[k] + int(shape_xy[k]) * resolution for k in range(2))
    per_m = scale / resolution
    x_ticks = _ticks(lo_m[0], hi_m[0], per_m, lambda m: left + (m - lo_m[0]) * per_m)
    y_ticks = _ticks(lo_m[1], hi_m[1], per_m, lambda m: map_box[3] - (m - lo_m[1]) * per_m)
    bar_m = round_length(max(SCALE_BAR_FRACTION * (hi_m[0] - lo_m[0]), resolution))
    bar_row = map_box[3] + AXIS_HEIGHT + SCALE_BAR_HEIGHT // 2
    scale_bar = (left, left + int(round(bar_m * per_m)), bar_row)
    canvas_w = max(map_box[2] + MARGIN_RIGHT, MIN_WIDTH, int(text_width(title)) + 8,
                   scale_bar[1] + 16 + int(text_width(f"{metres_text(bar_m)} m")))

    layout_tracks = []

    def pixel(xy_m):
        return map_pixel(map_box, lo_m, per_m, xy_m)

    for vid, xy in sorted((tracks or {}).items()):
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        xy = xy[np.isfinite(xy).all(axis=1)]
        if not len(xy):
            continue
        points = [pixel(p) for p in xy]
        end = points[-1]
        layout_tracks.append(Track(int(vid), points, f"drone {vid}", (end[0] + 6, end[1] - 14)))

    labels = [*class_labels, *(f"drone {t.vehicle_id} track" for t in layout_tracks)]
    legend, x, y = [], 4, scale_bar[2] + SCALE_BAR_HEIGHT // 2
    for label in labels:
        entry_w = 16 + int(text_width(label)) + 14
        if x > 4 and x + entry_w > canvas_w:
            x, y = 4, y + LEGEND_ROW
        legend.append((x, y, label))
        x += entry_w
    for note in notes:
        y += LEGEND_ROW
        legend.append((4, y, note))
        canvas_w = max(canvas_w, 8 + int(text_width(note)))
    origin = pixel((0.0, 0.0))
    inside = map_box[0] <= origin[0] <= map_box[2] and map_box[1] <= origin[1] <= map_box[3]
    return TopLayout(size=(canvas_w, y + LEGEND_ROW + 2), scale=scale, resolution=resolution, map_box=map_box,
                     lo_m=lo_m, title=title, title_px=(4, 4), x_ticks=x_ticks, y_ticks=y_ticks,
                     scale_bar=scale_bar, scale_bar_m=bar_m, origin_px=origin if inside else None,
                     tracks=layout_tracks, legend=legend, swatches=len(labels))

"""PNG views of a map: top view and horizontal slices, north up, with a colour legend."""

import io
from typing import TYPE_CHECKING

import numpy as np

from coopd.grid import OccupancyGrid, transform_grid
from coopd.grid.cells import OCCUPIED_THRESHOLD

from .atomic import write_atomic
from .png_layout import TopLayout, top_layout

if TYPE_CHECKING:
    from PIL import Image

UNKNOWN, FREE, OCCUPIED, INACCESSIBLE = 0, 1, 2, 3
COLOURS = np.array([(128, 128, 128), (255, 255, 255), (0, 0, 0), (200, 0, 0)], dtype=np.uint8)
LABELS = ("unknown", "free", "occupied", "inaccessible")
TRACK_COLOURS = ((0, 90, 220), (230, 120, 0), (0, 150, 60), (190, 0, 190), (0, 160, 170),
                 (140, 90, 20), (90, 60, 200), (220, 0, 90), (100, 130, 0), (0, 60, 120))
"""One colour per drone track, none of them a class colour (drones beyond ten reuse them)."""
ORIGIN_COLOUR = (0, 150, 0)
LEGEND_HEIGHT = 24
LEGEND_MIN_WIDTH = 360
TARGET_SIZE = 512
NEITHER, SEEN_FREE, ONLY_A, ONLY_B, BOTH = 0, 1, 2, 3, 4
MERGE_COLOURS = np.array([(160, 160, 160), (255, 255, 255), (0, 90, 220), (230, 80, 0), (0, 0, 0)],
                         dtype=np.uint8)
MERGE_LABELS = ("unknown", "free", "map A", "map B", "both")
"""Small maps are scaled up by a whole factor until their longer side is about this many pixels."""


def classify(cells: np.ndarray, threshold: int = OCCUPIED_THRESHOLD) -> np.ndarray:
    """Per-cell class (UNKNOWN/FREE/OCCUPIED/INACCESSIBLE) as uint8."""
    out = np.zeros(cells.shape, dtype=np.uint8)
    out[cells == -2] = INACCESSIBLE
    out[(cells >= 0) & (cells < threshold)] = FREE
    out[cells >= threshold] = OCCUPIED
    return out


def floor_and_ceiling_layers(cells: np.ndarray, threshold: int = OCCUPIED_THRESHOLD) -> np.ndarray:
    """z indices of the floor and ceiling: layers in the lowest or highest quarter of the known
    height band holding far more occupied cells than a typical layer (and their neighbours, for
    a surface one cell thick that straddles two layers)."""
    occupied = (cells >= threshold).sum(axis=(0, 1))
    known = np.nonzero((cells != -1).any(axis=(0, 1)))[0]
    if len(known) < 8:
        return np.zeros(0, dtype=np.int64)
    lo, hi = int(known[0]), int(known[-1])
    typical = max(float(np.median(occupied[lo:hi + 1])), 1.0)
    quarter = (hi - lo + 1) // 4
    surfaces = [z for z in range(lo, hi + 1)
                if occupied[z] > 4 * typical and (z < lo + quarter or z > hi - quarter)]
    layers = {n for z in surfaces for n in (z - 1, z, z + 1) if lo <= n <= hi}
    return np.array(sorted(layers), dtype=np.int64)


def top_classes(grid: OccupancyGrid, threshold: int = OCCUPIED_THRESHOLD) -> np.ndarray:
    """(m_x, m_y) classes seen from above, like a floor plan: occupied if any cell of the column
    is (floor and ceiling left out, or every indoor column would be occupied), else free, …"""
    cells = grid.cells
    skip = floor_and_ceiling_layers(cells, threshold)
    if len(skip):
        cells = np.delete(cells, skip, axis=2)
    out = np.zeros(grid.shape[:2], dtype=np.uint8)
    out[(cells == -2).any(axis=2)] = INACCESSIBLE
    out[((cells >= 0) & (cells < threshold)).any(axis=2)] = FREE
    out[(cells >= threshold).any(axis=2)] = OCCUPIED
    return out


def slice_classes(grid: OccupancyGrid, z_m: float, threshold: int = OCCUPIED_THRESHOLD) -> np.ndarray:
    """(m_x, m_y) classes of the horizontal layer holding height z_m (metres, map frame)."""
    key = int(np.floor(z_m / grid.resolution + 0.5))
    z = key - int(grid.offset[2])
    if not 0 <= z < grid.shape[2]:
        lo, hi = grid.bounds_m()
        raise ValueError(f"z = {z_m} m is outside the map (z from {lo[2]:.3f} to {hi[2]:.3f} m)")
    return classify(grid.cells[:, :, z], threshold)


class PillowMissing(ImportError):
    """PNG export without Pillow, which the drone install leaves out (it comes with the tools extra)."""

    extra = "tools"
    """The coopd extra that brings what is missing (command-line tools report it, no traceback)."""


def _pillow():
    """PIL's Image, ImageDraw and PngImagePlugin, imported on first use: maps load, convert to the
    other formats and travel without Pillow; only drawing a PNG needs it."""
    try:
        from PIL import Image, ImageDraw, PngImagePlugin
    except ImportError as e:
        raise PillowMissing("PNG export needs Pillow, which comes with coopd's tools extra: "
                            "pip install 'coopd[tools]' (or scripts/install --extras tools)") from e
    return Image, ImageDraw, PngImagePlugin


def scale_for(shape_xy) -> int:
    return max(1, min(16, TARGET_SIZE // max(shape_xy)))


def render(classes: np.ndarray, title: str, colours: np.ndarray = COLOURS, labels=LABELS) -> "Image.Image":
    """An RGB image of (m_x, m_y) classes, x to the right, y (north) up, legend underneath."""
    Image, ImageDraw, _ = _pillow()
    s = scale_for(classes.shape)
    rgb = _class_pixels(classes, colours, s)
    h, w = rgb.shape[:2]
    canvas = Image.new("RGB", (max(w, LEGEND_MIN_WIDTH), h + LEGEND_HEIGHT), (255, 255, 255))
    canvas.paste(Image.fromarray(rgb, "RGB"), (0, 0))
    draw = ImageDraw.Draw(canvas)
    x = 4
    for colour, label in zip(colours, labels, strict=True):
        _swatch(draw, (x, h + 6), colour, label)
        x += 20 + int(draw.textlength(label)) + 10
    canvas.info["Title"] = title
    return canvas


def _class_pixels(classes: np.ndarray, colours: np.ndarray, scale: int) -> np.ndarray:
    """(rows, columns, 3) colours of (m_x, m_y) classes, north up, each cell scale x scale pixels."""
    rgb = colours[classes.T[::-1]]
    return np.repeat(np.repeat(rgb, scale, axis=0), scale, axis=1)


def _swatch(draw, at, colour, label: str) -> None:
    """One legend entry: a 12-pixel colour square with its label to the right."""
    x, y = at
    draw.rectangle([x, y, x + 12, y + 12], fill=tuple(int(c) for c in colour), outline=(0, 0, 0))
    draw.text((x + 16, y), label, fill=(0, 0, 0))


def _save(image: "Image.Image", path) -> None:
    PngImagePlugin = _pillow()[2]
    buf = io.BytesIO()
    meta = PngImagePlugin.PngInfo()
    meta.add_text("Title", image.info.get("Title", "coopd map"))
    image.save(buf, format="PNG", pnginfo=meta)
    write_atomic(path, buf.getvalue())


def map_title(resolution: float, vehicle_id: int | None = None, stamp: float | None = None) -> str:
    """A top view's title: whose map, when (UTC), the resolution."""
    import datetime

    parts = ["coopd map" if vehicle_id is None else f"coopd map of vehicle {vehicle_id}"]
    if stamp:
        when = datetime.datetime.fromtimestamp(stamp, datetime.UTC)
        parts.append(when.strftime("%Y-%m-%d %H:%M:%S UTC"))
    return ", ".join([*parts, f"{resolution:g} m/cell"])


def top_view_layout(grid: OccupancyGrid, title: str, tracks=None, notes=(), text_width=None) -> TopLayout:
    """The layout export_png_top draws for `grid` (see coopd.io.png_layout.top_layout)."""
    extra = {} if text_width is None else {"text_width": text_width}
    return top_layout(grid.shape[:2], grid.offset[:2], grid.resolution, scale_for(grid.shape[:2]), title,
                      LABELS, tracks, notes, **extra)


def render_top(classes: np.ndarray, layout: TopLayout) -> "Image.Image":
    """A floor-plan top view: classes (m_x, m_y) north up with metre axes, the map origin, a scale
    bar, the drones' tracks and final positions, the title above and the legend underneath."""
    Image, ImageDraw, _ = _pillow()
    black = (0, 0, 0)
    canvas = Image.new("RGB", layout.size, (255, 255, 255))
    left, top, right, bottom = layout.map_box
    canvas.paste(_map_with_tracks(classes, layout), (left, top))
    draw = ImageDraw.Draw(canvas)
    draw.text(layout.title_px, layout.title, fill=black)
    draw.rectangle([left - 1, top - 1, right, bottom], outline=black)
    for x, label in layout.x_ticks:
        draw.line([x, bottom, x, bottom + 4], fill=black)
        draw.text((x - draw.textlength(label) / 2, bottom + 5), label, fill=black)
    for y, label in layout.y_ticks:
        draw.line([left - 5, y, left - 1, y], fill=black)
        draw.text((left - 8 - draw.textlength(label), y - 6), label, fill=black)
    draw.text((right + 4, bottom + 5), "m", fill=black)
    x0, x1, y = layout.scale_bar
    draw.rectangle([x0, y - 2, x1 - 1, y + 2], fill=black)
    draw.text((x1 + 8, y - 6), f"{layout.scale_bar_m:g} m", fill=black)
    swatch_colours = [*COLOURS, *(TRACK_COLOURS[k % len(TRACK_COLOURS)] for k in range(len(layout.tracks)))]
    for k, (x, y, label) in enumerate(layout.legend):
        if k < layout.swatches:
            _swatch(draw, (x, y), swatch_colours[k], label)
        else:
            draw.text((x, y), label, fill=black)
    canvas.info["Title"] = layout.title
    return canvas


def _map_with_tracks(classes: np.ndarray, layout: TopLayout) -> "Image.Image":
    """The map's pixels with the origin marker and the tracks drawn on them, cut at the map's
    edges (a track leaving the mapped area must not run over the axes or the title)."""
    Image, ImageDraw, _ = _pillow()
    image = Image.fromarray(_class_pixels(classes, COLOURS, layout.scale), "RGB")
    draw = ImageDraw.Draw(image)
    left, top = layout.map_box[:2]

    def here(point):
        return point[0] - left, point[1] - top

    if layout.origin_px is not None:
        ox, oy = here(layout.origin_px)
        draw.line([ox - 7, oy, ox + 7, oy], fill=ORIGIN_COLOUR, width=2)
        draw.line([ox, oy - 7, ox, oy + 7], fill=ORIGIN_COLOUR, width=2)
        draw.text((ox - 4 - draw.textlength("origin"), oy + 3), "origin", fill=ORIGIN_COLOUR)
    for k, track in enumerate(layout.tracks):
        colour = TRACK_COLOURS[k % len(TRACK_COLOURS)]
        points = [here(p) for p in track.points_px]
        if len(points) > 1:
            draw.line(points, fill=colour, width=2, joint="curve")
        ex, ey = points[-1]
        draw.ellipse([ex - 5, ey - 5, ex + 5, ey + 5], fill=colour, outline=(0, 0, 0))
        draw.text(here(track.label_px), track.label, fill=colour)
    return image


def export_png_top(grid: OccupancyGrid, path, threshold: int = OCCUPIED_THRESHOLD, title: str = "",
                   tracks=None, notes=()) -> TopLayout:
    """Top view of the whole map as a PNG: metre axes, origin, scale bar, title, legend and, when
    given, each drone's track ({vehicle id: (N, 2) metres in this map's frame}) with its final
    position. `notes` are extra legend lines. Returns the layout drawn."""
    layout = top_view_layout(grid, title or map_title(grid.resolution), tracks, notes, _pillow_text_width())
    _save(render_top(top_classes(grid, threshold), layout), path)
    return layout


def _pillow_text_width():
    """How wide Pillow's default font draws a line, for the layout to leave room for it."""
    Image, ImageDraw, _ = _pillow()
    return ImageDraw.Draw(Image.new("RGB", (1, 1))).textlength


def export_png_slice(grid: OccupancyGrid, path, z_m: float, threshold: int = OCCUPIED_THRESHOLD) -> None:
    """The horizontal slice at height z_m as a PNG with a legend."""
    classes = slice_classes(grid, z_m, threshold)
    _save(render(classes, f"coopd map slice z = {z_m} m, {grid.resolution} m/cell"), path)


def merge_classes(a: OccupancyGrid, b: OccupancyGrid, threshold: int = OCCUPIED_THRESHOLD) -> np.ndarray:
    """(m_x, m_y) top-view classes of two maps in one frame over both maps' extent: structure of A
    only, of B only, of both (the merge fits where walls overlap), else seen free, else unknown."""
    lo = np.minimum(a.offset[:2], b.offset[:2])
    hi = np.maximum(a.offset[:2] + a.shape[:2], b.offset[:2] + b.shape[:2])
    occupied = []
    seen = np.zeros(tuple(int(v) for v in hi - lo), dtype=bool)
    for g in (a, b):
        top = top_classes(g, threshold)
        start = g.offset[:2] - lo
        at = tuple(slice(int(s), int(s + n)) for s, n in zip(start, g.shape[:2], strict=True))
        occ = np.zeros_like(seen)
        occ[at] = top == OCCUPIED
        seen[at] |= top != UNKNOWN
        occupied.append(occ)
    out = np.where(seen, SEEN_FREE, NEITHER).astype(np.uint8)
    out[occupied[0] & ~occupied[1]] = ONLY_A
    out[occupied[1] & ~occupied[0]] = ONLY_B
    out[occupied[0] & occupied[1]] = BOTH
    return out


def export_png_merge(a: OccupancyGrid, b: OccupancyGrid, a_from_b, path, title: str = "",
                     threshold: int = OCCUPIED_THRESHOLD) -> None:
    """Top view of a merge: map A and map B carried into A's frame by a_from_b, one colour each."""
    classes = merge_classes(a, transform_grid(b, a_from_b), threshold)
    title = title or f"coopd merge top view, {a.resolution} m/cell"
    _save(render(classes, title, MERGE_COLOURS, MERGE_LABELS), path)

"""PNG views of a map: top view and horizontal slices, north up, with a colour legend."""

import io

import numpy as np
from PIL import Image, ImageDraw, PngImagePlugin

from coopd.grid import OccupancyGrid
from coopd.grid.cells import OCCUPIED_THRESHOLD

from .atomic import write_atomic

UNKNOWN, FREE, OCCUPIED, INACCESSIBLE = 0, 1, 2, 3
COLOURS = np.array([(128, 128, 128), (255, 255, 255), (0, 0, 0), (200, 0, 0)], dtype=np.uint8)
LABELS = ("unknown", "free", "occupied", "inaccessible")
LEGEND_HEIGHT = 24
LEGEND_MIN_WIDTH = 360
TARGET_SIZE = 512
"""Small maps are scaled up by a whole factor until their longer side is about this many pixels."""


def classify(cells: np.ndarray, threshold: int = OCCUPIED_THRESHOLD) -> np.ndarray:
    """Per-cell class (UNKNOWN/FREE/OCCUPIED/INACCESSIBLE) as uint8."""
    out = np.zeros(cells.shape, dtype=np.uint8)
    out[cells == -2] = INACCESSIBLE
    out[(cells >= 0) & (cells < threshold)] = FREE
    out[cells >= threshold] = OCCUPIED
    return out


def top_classes(grid: OccupancyGrid, threshold: int = OCCUPIED_THRESHOLD) -> np.ndarray:
    """(m_x, m_y) classes seen from above: occupied if any cell of the column is, else free, …"""
    cells = grid.cells
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


def scale_for(shape_xy) -> int:
    return max(1, min(16, TARGET_SIZE // max(shape_xy)))


def render(classes: np.ndarray, title: str) -> Image.Image:
    """An RGB image of (m_x, m_y) classes, x to the right, y (north) up, legend underneath."""
    s = scale_for(classes.shape)
    rgb = COLOURS[classes.T[::-1]]
    rgb = np.repeat(np.repeat(rgb, s, axis=0), s, axis=1)
    h, w = rgb.shape[:2]
    canvas = Image.new("RGB", (max(w, LEGEND_MIN_WIDTH), h + LEGEND_HEIGHT), (255, 255, 255))
    canvas.paste(Image.fromarray(rgb, "RGB"), (0, 0))
    draw = ImageDraw.Draw(canvas)
    x = 4
    for colour, label in zip(COLOURS, LABELS, strict=True):
        draw.rectangle([x, h + 6, x + 12, h + 18], fill=tuple(int(c) for c in colour), outline=(0, 0, 0))
        draw.text((x + 16, h + 6), label, fill=(0, 0, 0))
        x += 20 + int(draw.textlength(label)) + 10
    canvas.info["Title"] = title
    return canvas


def _save(image: Image.Image, path) -> None:
    buf = io.BytesIO()
    meta = PngImagePlugin.PngInfo()
    meta.add_text("Title", image.info.get("Title", "coopd map"))
    image.save(buf, format="PNG", pnginfo=meta)
    write_atomic(path, buf.getvalue())


def export_png_top(grid: OccupancyGrid, path, threshold: int = OCCUPIED_THRESHOLD) -> None:
    """Top view of the whole map as a PNG with a legend."""
    _save(render(top_classes(grid, threshold), f"coopd map top view, {grid.resolution} m/cell"), path)


def export_png_slice(grid: OccupancyGrid, path, z_m: float, threshold: int = OCCUPIED_THRESHOLD) -> None:
    """The horizontal slice at height z_m as a PNG with a legend."""
    classes = slice_classes(grid, z_m, threshold)
    _save(render(classes, f"coopd map slice z = {z_m} m, {grid.resolution} m/cell"), path)

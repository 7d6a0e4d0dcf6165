"""Solid primitives a world is made of: MJCF emission and exact cell-overlap tests for voxelising."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

EPS = 1e-6  # metres: faces exactly on a cell boundary do not mark the neighbouring cell


@dataclass(frozen=True)
class Box:
    """An axis-aligned solid box given by its centre and half extents (metres, world frame)."""

    name: str
    center: tuple[float, float, float]
    half: tuple[float, float, float]
    rgba: tuple[float, float, float, float] = (0.7, 0.7, 0.7, 1.0)

    def mjcf(self) -> str:
        """Return the MJCF <geom> element for this box."""
        c, h, r = self.center, self.half, self.rgba
        return (
            f'<geom name="{self.name}" type="box" pos="{c[0]:.4f} {c[1]:.4f} {c[2]:.4f}" '
            f'size="{h[0]:.4f} {h[1]:.4f} {h[2]:.4f}" rgba="{r[0]} {r[1]} {r[2]} {r[3]}"/>'
        )

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Return (min corner, max corner) of the box."""
        c, h = np.array(self.center), np.array(self.half)
        return c - h, c + h

    def overlaps_cells(self, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
        """True where the open cells [lo, hi] (arrays (..., 3)) share volume with the box."""
        bmin, bmax = self.bounds()
        return np.all((lo < bmax - EPS) & (hi > bmin + EPS), axis=-1)


@dataclass(frozen=True)
class Cylinder:
    """A vertical (z-axis) solid cylinder given by its centre, radius and half height."""

    name: str
    center: tuple[float, float, float]
    radius: float
    half_height: float
    rgba: tuple[float, float, float, float] = (0.6, 0.5, 0.4, 1.0)

    def mjcf(self) -> str:
        """Return the MJCF <geom> element for this cylinder."""
        c, r = self.center, self.rgba
        return (
            f'<geom name="{self.name}" type="cylinder" pos="{c[0]:.4f} {c[1]:.4f} {c[2]:.4f}" '
            f'size="{self.radius:.4f} {self.half_height:.4f}" rgba="{r[0]} {r[1]} {r[2]} {r[3]}"/>'
        )

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Return (min corner, max corner) of the cylinder's bounding box."""
        c = np.array(self.center)
        h = np.array([self.radius, self.radius, self.half_height])
        return c - h, c + h

    def overlaps_cells(self, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
        """True where the open cells [lo, hi] share volume with the cylinder (exact for z-aligned cells)."""
        c = np.array(self.center)
        nearest = np.clip(c[:2], lo[..., :2], hi[..., :2])
        d2 = np.sum((nearest - c[:2]) ** 2, axis=-1)
        z_ok = (lo[..., 2] < c[2] + self.half_height - EPS) & (hi[..., 2] > c[2] - self.half_height + EPS)
        return (d2 < (self.radius - EPS) ** 2) & z_ok


Shape = Box | Cylinder


def box_from_corners(name: str, lo, hi, rgba=(0.7, 0.7, 0.7, 1.0)) -> Box:
    """Build a Box from its min and max corners."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    c, h = (lo + hi) / 2.0, (hi - lo) / 2.0
    return Box(name, tuple(float(v) for v in c), tuple(float(v) for v in h), rgba)

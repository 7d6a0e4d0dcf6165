"""Maps on disk: .cmap files (one wire message), OctoMap .bt / .ot files read, and exports to PLY,
PNG and OctoMap .bt."""

from .bt import export_bt
from .cmap import load_cmap, save_cmap
from .maps import load_map
from .ply import export_ply
from .png import export_png_slice, export_png_top

__all__ = ["export_bt", "export_ply", "export_png_slice", "export_png_top", "load_cmap", "load_map",
           "save_cmap"]

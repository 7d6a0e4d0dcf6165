"""Reading any map file coopctl takes: coopd .cmap messages and OctoMap .bt / .ot trees, told apart
by their content (not their suffix)."""

from coopd.grid import OccupancyGrid
from coopd.sharing.wire import DEFAULT_LIMITS, DecodeLimits, MapMeta, WireError, decode_map

from .bt import is_octomap, read_octomap
from .cmap import read_cmap_bytes

FOREIGN_VEHICLE_ID = 0
"""The vehicle id given to a map that came from another mapper (an OctoMap file carries none)."""


def load_map(path, limits: DecodeLimits = DEFAULT_LIMITS) -> tuple[OccupancyGrid, MapMeta]:
    """The grid and metadata of a .cmap file, or of an OctoMap .bt / .ot file (vehicle id 0, version 0);
    errors name the file."""
    data = read_cmap_bytes(path, limits)
    try:
        if is_octomap(data):
            return read_octomap(data, limits.max_cells), MapMeta(FOREIGN_VEHICLE_ID)
        return decode_map(data, limits)
    except WireError as e:
        raise WireError(f"{path}: {e}") from e
    except ValueError as e:
        raise ValueError(f"{path}: {e}") from e

"""coopd: cooperative 3D occupancy mapping for drone swarms."""

import os
import tempfile

__version__ = "0.1.0"


def _ensure_numba_cache_dir() -> None:
    """numba's on-disk cache (cache=True) needs a writable directory, or importing a kernel fails
    ("no locator available"). Under systemd the unit sets NUMBA_CACHE_DIR; for anyone else
    running coopctl from a read-only install without a writable home, use a per-user temp dir."""
    if os.environ.get("NUMBA_CACHE_DIR"):
        return
    if os.access(os.path.dirname(os.path.abspath(__file__)), os.W_OK):
        return
    home = os.path.expanduser("~")
    if home != "~" and os.path.isdir(home) and os.access(home, os.W_OK):
        return
    os.environ["NUMBA_CACHE_DIR"] = os.path.join(tempfile.gettempdir(), f"coopd-numba-{os.getuid()}")


_ensure_numba_cache_dir()

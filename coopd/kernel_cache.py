"""Whether numba may keep this process' compiled kernels on disk (`cache=` of every coopd kernel).

numba looks, in order, at $NUMBA_CACHE_DIR (the unit sets it to its CacheDirectory), a
__pycache__ next to the sources (a checkout, a user's own venv) and the user's cache directory
($XDG_CACHE_HOME or ~/.cache). With none of them writable (a system install used by an account
without a home) a kernel declared with cache=True cannot even be defined, so the kernels are then
compiled in memory for this process only: slower to start, never a shared directory that another
local user could fill with code for us to load. Decided once, without changing os.environ.
"""

import os
import tempfile

PACKAGE_DIR = os.path.dirname(os.path.abspath(__file__))


def _usable(path: str) -> bool:
    """numba's own test of a cache directory: create it, then a file in it."""
    try:
        os.makedirs(path, exist_ok=True)
        tempfile.TemporaryFile(dir=path).close()
    except OSError:
        return False
    return True


def can_cache(environ=os.environ, package_dir: str = PACKAGE_DIR) -> bool:
    """True when one of numba's cache locations is usable by this process."""
    if environ.get("NUMBA_CACHE_DIR"):
        return True  # an explicit choice: numba uses it (and says so if it cannot)
    if _usable(os.path.join(package_dir, "__pycache__")):
        return True
    user_cache = environ.get("XDG_CACHE_HOME", os.path.expanduser("~/.cache"))  # numba's expression
    return os.path.isabs(user_cache) and _usable(os.path.join(user_cache, "numba"))


CACHE = can_cache()
"""Passed as cache= to numba.njit by every coopd kernel."""

"""Camera-test setup: the real firmware_sim package (tests/firmware_sim shadows it on sys.path when
tests/ comes first)."""

import importlib
import os
import sys

_ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
_loaded = sys.modules.get("firmware_sim")
if _loaded is None or os.path.dirname(os.path.dirname(getattr(_loaded, "__file__", "") or "")) != _ROOT:
    sys.modules.pop("firmware_sim", None)
    sys.path.insert(0, _ROOT)
    importlib.import_module("firmware_sim")
    sys.path.remove(_ROOT)

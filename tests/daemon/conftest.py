"""Fixtures of the daemon tests."""

import json
from pathlib import Path

import numpy as np
import pytest

from coopd.io.cmap import load_cmap

DATA = Path(__file__).parents[1] / "merging" / "data" / "small_house_flip"


@pytest.fixture(scope="module")
def flip():
    """({"early": [map 1, map 2], "later": [...]}, true transform 1<-2, the mirror fit the daemons
    accepted on the early maps)."""
    info = json.loads((DATA / "truth.json").read_text())
    maps = {name: [load_cmap(DATA / f"{name}_{i}.cmap")[0] for i in (1, 2)] for name in ("early", "later")}
    return maps, np.array(info["truth_1_from_2"]), np.array(info["accepted_early_1_from_2"])

"""simset's camera rate: it reaches the emulated cameras, and a flight at another rate (or mapped with
other settings) is cached apart."""

from pathlib import Path

import pytest

from coopd.mapping import MapperConfig
from firmware_sim import simset


def test_cache_path_names_a_camera_rate_other_than_the_default():
    def path(rate=None):
        return simset.cache_path("bookstore", 1, 30, 1, 0.0, 0.0, Path("c"), rate)

    tag = simset.mapper_tag()
    assert path() == Path(f"c/bookstore_s1_n30_m{tag}.npz")
    assert path(simset.camera().rate_hz) == path()
    assert path(2.5) == Path(f"c/bookstore_s1_n30_c2.5_m{tag}.npz")


def test_flights_mapped_with_other_mapper_settings_are_cached_apart():
    """A cache made before the mapper's defaults changed must not pass for today's flights."""
    assert simset.mapper_tag() == simset.mapper_tag(MapperConfig(threads=4))
    assert simset.mapper_tag() != simset.mapper_tag(MapperConfig(graze_deg=0.0))
    assert simset.mapper_tag() != simset.mapper_tag(MapperConfig(miss_decrement=14))
    other = simset.cache_path("bookstore", 1, 3, 1, 0.0, 0.0, Path("c"), mapper=MapperConfig(graze_deg=0.0))
    assert other != simset.cache_path("bookstore", 1, 3, 1, 0.0, 0.0, Path("c"))


@pytest.mark.parametrize("rate", [0.0, -1.0, float("nan"), 5000.0])
def test_a_camera_rate_the_emulator_cannot_honour_is_refused(rate):
    with pytest.raises(ValueError, match="rate"):
        simset.camera(rate)


def test_the_camera_rate_sets_the_frames_mapped():
    """Three simulated seconds of one drone: about rate x 3 s frames each way."""
    slow = simset.fly("small_house", 1, n_vehicles=1, max_flight_s=3.0, camera_rate_hz=2.0)[0]
    fast = simset.fly("small_house", 1, n_vehicles=1, max_flight_s=3.0)[0]
    assert 6 <= slow.frames <= 8, slow.frames
    assert 30 <= fast.frames <= 32, fast.frames
    assert 0 < slow.grid.size and 0 < fast.grid.size

"""simset's camera rate: it reaches the emulated cameras, and a flight at another rate is cached apart."""

from pathlib import Path

import pytest

from firmware_sim import simset


def test_cache_path_names_a_camera_rate_other_than_the_default():
    def path(rate=None):
        return simset.cache_path("bookstore", 1, 30, 1, 0.0, 0.0, Path("c"), rate)

    assert path() == Path("c/bookstore_s1_n30.npz")
    assert path(simset.camera().rate_hz) == path()
    assert path(2.5) == Path("c/bookstore_s1_n30_c2.5.npz")


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

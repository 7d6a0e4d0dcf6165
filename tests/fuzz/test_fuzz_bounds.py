"""The contract checks themselves: a hang, an over-allocation and a stray exception type are findings."""

import time

import numpy as np
import pytest

from tests.fuzz.bounds import Finding, allocation_limit, expect_only, time_limit
from tests.fuzz.mutate import MUTATORS, mutate


def test_a_hang_is_a_finding():
    with pytest.raises(Finding, match="hang"), time_limit(0.2, "spin"):
        while True:
            time.sleep(0.01)


def test_an_allocation_beyond_the_bound_is_a_finding():
    with pytest.raises(Finding, match="allocated"), allocation_limit(1 << 20, "big"):
        np.ones(4 << 20, dtype=np.uint8)
    with allocation_limit(1 << 20, "small"):
        np.ones(1 << 10, dtype=np.uint8)


def test_only_documented_errors_with_a_message_pass():
    assert expect_only(ValueError, "v", lambda: int("x")) is None
    with pytest.raises(Finding, match="undocumented KeyError"):
        expect_only(ValueError, "k", lambda: {}["missing"])
    with pytest.raises(Finding, match="without a message"):
        expect_only(ValueError, "m", lambda: (_ for _ in ()).throw(ValueError()))


def test_mutants_differ_from_their_seed_and_stay_bounded():
    import random

    rng = random.Random(0)
    seed = bytes(range(256)) * 4
    mutants = [mutate(seed, rng, [seed, b"xyz"], max_len=2000) for _ in range(300)]
    assert sum(m != seed for m in mutants) > 280
    assert all(len(m) <= 2000 for m in mutants)
    for mutator in MUTATORS:
        assert isinstance(mutator(bytearray(b""), rng, [b"ab"]), bytearray)

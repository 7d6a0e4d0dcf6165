"""Fuzz map deltas (coopd.sharing.delta.apply_delta on a held map): mutants, random bytes and header fields
set to arbitrary values are refused with a WireError or give the map their header names; the held map is
never changed."""

import struct

from hypothesis import given
from hypothesis import strategies as st

from coopd.sharing import delta
from tests.fuzz.ci_budget import CI_SETTINGS, assert_mutations_clean
from tests.fuzz.harness import DeltaTarget

DELTA = DeltaTarget()


def test_the_seeds_apply():
    for seed in DELTA.seeds():
        assert delta.apply_delta(DELTA.base, DELTA.base_meta, seed) is not None


def test_mutated_deltas_keep_the_contract():
    assert_mutations_clean(DELTA)


@CI_SETTINGS
@given(st.binary(max_size=400))
def test_random_deltas(data):
    DELTA.check(bytes([delta.MSG_MAP_DELTA]) + data)


@CI_SETTINGS
@given(st.sampled_from(DELTA.seeds()), st.data())
def test_header_fields_set_to_arbitrary_values(seed, data):
    """Any field of a valid header rewritten (shape, offset, versions, counts, sizes, CRCs, brick edge)."""
    fmt = data.draw(st.sampled_from(["<b", "<B", "<H", "<i", "<I", "<d", "<Q"]))
    size = struct.calcsize(fmt)
    off = data.draw(st.integers(0, delta.DELTA_HEADER.size - size))
    raw = data.draw(st.binary(min_size=size, max_size=size))
    DELTA.check(seed[:off] + raw + seed[off + size:])

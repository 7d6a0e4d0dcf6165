"""Fuzz the map serializer (peek, decode_map with DecodeLimits) and .cmap loading."""

import struct

import pytest
from hypothesis import given
from hypothesis import strategies as st

from coopd.sharing import wire
from tests.fuzz.ci_budget import CI_SETTINGS, assert_mutations_clean
from tests.fuzz.harness import CmapTarget, WireTarget

WIRE = WireTarget()
SEEDS = WIRE.seeds()


@pytest.fixture(scope="module")
def cmap_target(tmp_path_factory):
    return CmapTarget(tmp_path_factory.mktemp("cmap"))


def test_mutated_messages_keep_the_contract():
    assert_mutations_clean(WIRE)


def test_mutated_cmap_files_keep_the_contract(cmap_target):
    assert_mutations_clean(cmap_target, cases=500)


@CI_SETTINGS
@given(st.binary(max_size=400))
def test_random_messages(data):
    WIRE.check(data)


@CI_SETTINGS
@given(st.sampled_from(SEEDS), st.data())
def test_header_fields_set_to_arbitrary_values(seed, data):
    """Any field of a valid header rewritten (sizes, shape, offsets, resolution, CRC, encoding)."""
    header = wire.COOPD_HEADER.size if seed[0] == wire.MSG_COOPD_MAP else wire.THESIS_HEADER.size
    fmt = data.draw(st.sampled_from(["<b", "<B", "<H", "<i", "<I", "<f", "<d", "<Q"]))
    size = struct.calcsize(fmt)
    off = data.draw(st.integers(0, header - size))
    raw = data.draw(st.binary(min_size=size, max_size=size))
    WIRE.check(seed[:off] + raw + seed[off + size:])

"""Fuzz the map serializer (peek, decode_map with DecodeLimits) and .cmap loading."""

import random
import struct

import pytest
from hypothesis import given
from hypothesis import strategies as st

from coopd.sharing import wire
from tests.fuzz.ci_budget import CI_SETTINGS, assert_mutations_clean
from tests.fuzz.harness import CmapTarget, MergeResultTarget, WireTarget

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


MERGE_RESULT = MergeResultTarget()


def test_mutated_merge_results_keep_the_contract():
    assert_mutations_clean(MERGE_RESULT)


@CI_SETTINGS
@given(st.sampled_from(MERGE_RESULT.seeds()[1:]), st.data())
def test_merge_result_fields_set_to_arbitrary_values(seed, data):
    """Any 1-8 bytes of a valid merge result rewritten, the CRC fixed or not."""
    size = data.draw(st.integers(1, 8))
    off = data.draw(st.integers(0, len(seed) - size))
    raw = data.draw(st.binary(min_size=size, max_size=size))
    mutant = seed[:off] + raw + seed[off + size:]
    if data.draw(st.booleans()):
        mutant = MERGE_RESULT.post_mutate(mutant, random.Random(0))  # Random(0) draws 0.84: CRC fixed
    MERGE_RESULT.check(mutant)

"""Fuzz the thesis codec and the planes encoding: hostile streams give CodecError/PlanesError, bounded."""

import struct

import pytest
from hypothesis import given
from hypothesis import strategies as st

from tests.fuzz.ci_budget import CI_SETTINGS, assert_mutations_clean
from tests.fuzz.harness import SIZE_PREFIX, CodecTarget, PlanesTarget

CODEC = CodecTarget()
PLANES = PlanesTarget()

literal = st.integers(-2, 100).map(lambda v: [v])
triple = st.tuples(st.integers(-127, -10), st.integers(-128, 127), st.integers(-128, 127)).map(list)
token_stream = st.lists(st.one_of(literal, triple, st.integers(-128, 127).map(lambda v: [v])), max_size=40)


@pytest.mark.parametrize("target", [CODEC, PLANES], ids=lambda t: t.name)
def test_mutated_seeds_keep_the_contract(target):
    assert_mutations_clean(target)


@CI_SETTINGS
@given(st.integers(0, 1 << 20), st.binary(max_size=300))
def test_random_codec_streams(n, stream):
    CODEC.check(SIZE_PREFIX.pack(n) + stream)


@CI_SETTINGS
@given(st.integers(0, 1 << 20), token_stream)
def test_token_streams_near_the_grammar(n, tokens):
    stream = struct.pack(f"{sum(map(len, tokens))}b", *[b for t in tokens for b in t])
    CODEC.check(SIZE_PREFIX.pack(n) + stream)


@CI_SETTINGS
@given(st.integers(0, 1 << 16), st.lists(st.binary(max_size=40), min_size=3, max_size=3))
def test_planes_payloads_with_consistent_frame_sizes(n, frames):
    payload = struct.pack("<III", *map(len, frames)) + b"".join(frames)
    PLANES.check(SIZE_PREFIX.pack(n) + payload)

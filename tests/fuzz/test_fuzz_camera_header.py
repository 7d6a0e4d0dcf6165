"""Fuzz camera frame headers: length prefix and msgpack header give a FrameHeader or ProtocolError."""

import struct

import msgpack
from hypothesis import given
from hypothesis import strategies as st

from coopd.camera.protocol import FLOAT_FIELDS, INT_FIELDS
from tests.fuzz.ci_budget import CI_SETTINGS, assert_mutations_clean
from tests.fuzz.harness import CameraHeaderTarget

HEADER = CameraHeaderTarget()
msgpack_int = st.integers(-(2**63), 2**64 - 1)
any_value = st.one_of(st.none(), st.booleans(), msgpack_int, st.floats(), st.text(max_size=8),
                      st.binary(max_size=8), st.lists(msgpack_int, max_size=3),
                      st.dictionaries(st.text(max_size=3), msgpack_int, max_size=2))


def test_mutated_headers_keep_the_contract():
    assert_mutations_clean(HEADER, cases=3000)


@CI_SETTINGS
@given(st.binary(max_size=300))
def test_random_bytes(data):
    HEADER.check(struct.pack("<I", len(data)) + data)


@CI_SETTINGS
@given(st.dictionaries(st.sampled_from(INT_FIELDS + FLOAT_FIELDS + ("enc", "clock", "extra")), any_value),
       st.data())
def test_header_maps_with_arbitrary_field_values(over, data):
    good = msgpack.unpackb(HEADER.seeds()[0][4:])
    d = {**good, **over}
    if data.draw(st.booleans()):
        d["n"] = d["w"] * d["h"] * 2 if type(d["w"]) is type(d["h"]) is int else d["n"]
    raw = msgpack.packb(d, use_bin_type=True)
    HEADER.check(struct.pack("<I", len(raw)) + raw)

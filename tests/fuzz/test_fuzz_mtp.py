"""Fuzz MTP reassembly: any byte stream in any chunking gives events or MtpError, with bounded buffers."""

from hypothesis import given
from hypothesis import strategies as st

from coopd.sharing import mtp
from tests.fuzz.ci_budget import CI_SETTINGS, assert_mutations_clean
from tests.fuzz.harness import MTP_BS, MtpTarget

MTP = MtpTarget()

control_frame = st.builds(
    lambda kind, count, rest: bytes([mtp.MARK, kind]) + count.to_bytes(4, "little", signed=True)
    + rest.ljust(MTP_BS - 6, b"\0")[: MTP_BS - 6],
    st.integers(0, 255), st.integers(-(2**31), 2**31 - 1) | st.integers(-2, 1100), st.binary(max_size=60))
data_block = st.binary(min_size=MTP_BS, max_size=MTP_BS)


def test_mutated_streams_keep_the_contract():
    assert_mutations_clean(MTP)


@CI_SETTINGS
@given(st.binary(max_size=700))
def test_random_streams(data):
    MTP.check(data)


@CI_SETTINGS
@given(st.lists(st.one_of(control_frame, data_block), max_size=12))
def test_frame_sequences_with_arbitrary_counts(frames):
    MTP.check(MTP.seeds()[0] + b"".join(frames))

"""Fuzz the servers that face the network and local drivers: MTP server, control socket (and coopctl's
client of it), camera source, MAVLink udpin link. Each runs on loopback; every hostile connection must
end, and none may break the server."""

import random

import pytest
from hypothesis import given
from hypothesis import strategies as st

from tests.fuzz.ci_budget import CI_SETTINGS, assert_mutations_clean
from tests.fuzz.harness import (
    TRANSPORT_BS,
    CameraSocketTarget,
    ControlClientTarget,
    ControlTarget,
    MavlinkUdpTarget,
    TransportTarget,
    _mavlink_seeds,
)

SOCKET_CASES = 1000
SOCKET_SETTINGS = CI_SETTINGS.__class__(CI_SETTINGS, max_examples=60)


@pytest.fixture(scope="module")
def short_dir(tmp_path_factory):
    """A directory whose unix socket paths fit in sun_path."""
    import tempfile

    with tempfile.TemporaryDirectory(prefix="fz") as d:
        yield d


@pytest.fixture(scope="module")
def transport():
    with TransportTarget() as t:
        yield t


@pytest.fixture(scope="module")
def control(short_dir):
    with ControlTarget(short_dir) as t:
        yield t


@pytest.fixture(scope="module")
def camera(short_dir):
    with CameraSocketTarget(short_dir) as t:
        yield t


@pytest.fixture(scope="module")
def mavlink_udp():
    with MavlinkUdpTarget() as t:
        yield t


def test_mtp_server_survives_mutated_streams(transport):
    assert_mutations_clean(transport, cases=SOCKET_CASES)
    transport.good_peer_delivers()


@SOCKET_SETTINGS
@given(st.binary(max_size=2 * TRANSPORT_BS))
def test_mtp_server_survives_random_bytes_after_a_hello(transport, junk):
    transport.check(transport.seeds()[2] + junk)


def test_control_server_survives_mutated_requests(control):
    assert_mutations_clean(control, cases=SOCKET_CASES)


@SOCKET_SETTINGS
@given(st.recursive(st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=10),
                    lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=5), inner,
                                                                                 max_size=3), max_leaves=10),
       st.sampled_from(["status", "blob", "ping", "", "x" * 40]))
def test_control_server_answers_arbitrary_json(control, args, cmd):
    import json
    import struct

    body = json.dumps({"v": 1, "cmd": cmd, "args": args}).encode()
    control.check(struct.pack(">I", len(body)) + body)


@pytest.fixture(scope="module")
def control_client(short_dir):
    with ControlClientTarget(short_dir) as t:
        yield t


def test_control_client_survives_a_hostile_daemon(control_client):
    assert_mutations_clean(control_client, cases=SOCKET_CASES)


def test_camera_source_survives_a_hostile_driver(camera):
    assert_mutations_clean(camera, cases=400)
    assert camera.source.counters["frames"] > 0, "the valid seeds must have delivered frames"


def test_vehicle_link_survives_hostile_datagrams(mavlink_udp):
    assert_mutations_clean(mavlink_udp, cases=SOCKET_CASES)
    rng = random.Random(1)
    for _ in range(50):
        mavlink_udp.check(rng.randbytes(rng.randint(1, 300)))
    for seed in _mavlink_seeds():
        mavlink_udp.check(seed)
    status = mavlink_udp.link.status()["counters"]
    assert status["rx_bad_data"] + status.get("rx_parse_errors", 0) > 0, "drops must be counted"
    assert status["rx_messages"] > 0

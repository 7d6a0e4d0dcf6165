"""Connection strings as MAVLink users write them."""

import pytest

from coopd.vehicle.transport import (
    Endpoint,
    SerialTransport,
    SocketTransport,
    make_transport,
    parse_connection,
)


@pytest.mark.parametrize(
    "text, expected",
    [
        ("udpin:0.0.0.0:14540", Endpoint("udpin", "0.0.0.0", 14540)),
        ("udp:127.0.0.1:14550", Endpoint("udpin", "127.0.0.1", 14550)),
        ("udpout:10.0.0.2:14555", Endpoint("udpout", "10.0.0.2", 14555)),
        ("tcp:localhost:5760", Endpoint("tcp", "localhost", 5760)),
        ("/dev/ttyACM0,921600", Endpoint("serial", device="/dev/ttyACM0", baud=921600)),
        ("serial:/dev/ttyAMA0:57600", Endpoint("serial", device="/dev/ttyAMA0", baud=57600)),
    ],
)
def test_parses(text, expected):
    assert parse_connection(text) == expected


@pytest.mark.parametrize(
    "text",
    [
        "",
        "udpin:14540",
        "udpin:host:0",
        "udpin:host:99999",
        "tcp::5760x",
        "/dev/ttyACM0",
        "/dev/ttyACM0,fast",
        "ftp:host:1",
        "x" * 300,
    ],
)
def test_refuses_with_a_reason(text):
    with pytest.raises(ValueError):
        parse_connection(text)


def test_transport_kind():
    assert isinstance(make_transport("udpin:127.0.0.1:1"), SocketTransport)
    assert isinstance(make_transport("/dev/ttyUSB0,57600"), SerialTransport)


def test_missing_serial_device_is_an_oserror_not_a_crash():
    t = make_transport("/dev/coopd-no-such-tty,57600")
    with pytest.raises(OSError):
        t.open()
    assert not t.is_open and t.read(0.01) == b""

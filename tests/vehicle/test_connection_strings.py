"""Connection strings as MAVLink users write them: one parser for the config check and the link,
and every documented form really connects to a loopback FC (UDP, TCP, IPv6, a pty for serial)."""

import re
import socket
import time
import tomllib
from pathlib import Path

import pytest
from pymavlink.dialects.v20 import common as mav
from sim_helpers import wait_until

from coopd.daemon.config import ConfigError, parse_config
from coopd.vehicle.connection import DEFAULT_BAUD
from coopd.vehicle.link import LinkConfig, VehicleLink
from coopd.vehicle.transport import (
    Endpoint,
    SerialTransport,
    SocketTransport,
    TcpServerTransport,
    make_transport,
    parse_connection,
)
from tests.loopback import has_ipv6_loopback
from tests.loopback_fc import LOOPBACK, LoopbackFc, PtyChannel, TcpChannel, UdpChannel, free_port

REPO = Path(__file__).resolve().parents[2]


@pytest.mark.parametrize(
    "text, expected",
    [
        ("udpin:0.0.0.0:14540", Endpoint("udpin", "0.0.0.0", 14540)),
        ("udp:127.0.0.1:14550", Endpoint("udpin", "127.0.0.1", 14550)),
        ("udpout:10.0.0.2:14555", Endpoint("udpout", "10.0.0.2", 14555)),
        ("tcp:localhost:5760", Endpoint("tcp", "localhost", 5760)),
        ("/dev/ttyACM0,921600", Endpoint("serial", device="/dev/ttyACM0", baud=921600)),
        ("serial:/dev/ttyAMA0:57600", Endpoint("serial", device="/dev/ttyAMA0", baud=57600)),
        ("/dev/ttyACM0", Endpoint("serial", device="/dev/ttyACM0", baud=DEFAULT_BAUD)),
        ("serial:/dev/ttyS1", Endpoint("serial", device="/dev/ttyS1", baud=DEFAULT_BAUD)),
        ("serial:///dev/ttyACM0:57600", Endpoint("serial", device="/dev/ttyACM0", baud=57600)),
        ("tcpin:127.0.0.1:5760", Endpoint("tcpin", "127.0.0.1", 5760)),
        ("udpin://0.0.0.0:14540", Endpoint("udpin", "0.0.0.0", 14540)),
        ("udp://:14540", Endpoint("udpin", "0.0.0.0", 14540)),
        ("udpout://192.168.1.12:14550", Endpoint("udpout", "192.168.1.12", 14550)),
        ("tcp://127.0.0.1:5760", Endpoint("tcp", "127.0.0.1", 5760)),
        ("tcpout://fc.local:5760", Endpoint("tcp", "fc.local", 5760)),
        ("tcpin://:5760", Endpoint("tcpin", "0.0.0.0", 5760)),
        ("udpin:[::]:14540", Endpoint("udpin", "::", 14540)),
        ("udpout:[fe80::1]:14550", Endpoint("udpout", "fe80::1", 14550)),
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
        "/dev/ttyACM0,fast",
        "/dev/ttyACM0,0",
        "serial:ttyACM0",
        "serial:///dev/ttyACM0:fast",
        "udpin://0.0.0.0",
        "udpout::14550",
        "tcp://:5760",
        "udpin:::1:14540",
        "udpin:[nope]:14540",
        "udpin://host name:1",
        "udpbcast:10.0.0.255:14550",
        "udpin:1.2.3:14540",
        "udpin:-bad-:14540",
        "ftp:host:1",
        "x" * 300,
    ],
)
def test_refuses_with_a_reason(text):
    with pytest.raises(ValueError) as refused:
        parse_connection(text)
    with pytest.raises(ConfigError) as check:  # coopd --check-config refuses it with the same reason
        parse_config(f"[vehicle]\nmavlink = {text!r}")
    assert check.value.key == "vehicle.mavlink" and str(refused.value) in str(check.value)


def test_transport_kind():
    assert isinstance(make_transport("udpin:127.0.0.1:1"), SocketTransport)
    assert isinstance(make_transport("/dev/ttyUSB0,57600"), SerialTransport)
    assert isinstance(make_transport("tcpin:127.0.0.1:1"), TcpServerTransport)


def test_missing_serial_device_is_an_oserror_not_a_crash():
    t = make_transport("/dev/coopd-no-such-tty,57600")
    with pytest.raises(OSError):
        t.open()
    assert not t.is_open and t.read(0.01) == b""


# ------------------------------------------------------------------------- every form really connects
FC_SYSTEM = 7


def fc_channel(text: str, pty: PtyChannel | None = None):
    """The FC's end of the loopback channel a connection string describes (coopd holds the other)."""
    e = parse_connection(text)
    if e.kind == "serial":
        return pty
    family = socket.AF_INET6 if ":" in e.host else socket.AF_INET
    address = (LOOPBACK[family], e.port)
    return {
        "udpin": lambda: UdpChannel(family, send_to=address),
        "udpout": lambda: UdpChannel(family, bind_port=e.port),
        "tcp": lambda: TcpChannel(family, listen_port=e.port),
        "tcpin": lambda: TcpChannel(family, connect_to=address),
    }[e.kind]()


def connects(text: str, pty: PtyChannel | None = None) -> None:
    """coopd's link on `text` locks onto the loopback FC and the FC hears coopd's heartbeat."""
    fc = LoopbackFc(fc_channel(text, pty), system_id=FC_SYSTEM)
    link = VehicleLink(LinkConfig(connection=text, source_system=3))
    link.start()
    try:
        ours = lambda: [m for m in fc.messages("HEARTBEAT") if m.get_srcSystem() == 3]  # noqa: E731
        assert fc.run_until(lambda: link.state == "ok" and ours(), seconds=5.0), (text, link.status())
        assert link.target_system == FC_SYSTEM
        assert ours()[0].get_srcComponent() == mav.MAV_COMP_ID_ONBOARD_COMPUTER
        assert ours()[0].type == mav.MAV_TYPE_ONBOARD_CONTROLLER
    finally:
        link.stop()
        fc.close()


NETWORK_FORMS = [
    "udpin:127.0.0.1:{port}",
    "udp:127.0.0.1:{port}",
    "udpout:127.0.0.1:{port}",
    "tcp:127.0.0.1:{port}",
    "tcpin:127.0.0.1:{port}",
    "udpin://127.0.0.1:{port}",
    "udp://127.0.0.1:{port}",
    "udpout://127.0.0.1:{port}",
    "tcp://127.0.0.1:{port}",
    "tcpout://127.0.0.1:{port}",
    "tcpin://127.0.0.1:{port}",
    "tcp:localhost:{port}",
]
IPV6_FORMS = ["udpin:[::1]:{port}", "udpout:[::1]:{port}", "tcp://[::1]:{port}", "tcpin:[::1]:{port}"]
SERIAL_FORMS = ["{device}", "{device},115200", "serial:{device}", "serial:{device}:921600", "serial://{device}:57600"]


@pytest.mark.parametrize("form", NETWORK_FORMS)
def test_network_form_connects(form):
    connects(form.format(port=free_port()))


@pytest.mark.skipif(not has_ipv6_loopback(), reason="no IPv6 loopback (::1) on this machine")
@pytest.mark.parametrize("form", IPV6_FORMS)
def test_ipv6_form_connects(form):
    connects(form.format(port=free_port(socket.AF_INET6)))


@pytest.mark.parametrize("form", SERIAL_FORMS)
def test_serial_form_connects_over_a_pty(form):
    pty = PtyChannel()
    text = form.format(device=pty.path)
    assert parse_connection(text).device == pty.path
    connects(text, pty)


def documented_examples() -> list[str]:
    """The quoted connection strings in etc/coopd.toml's comment on vehicle.mavlink, and its value."""
    lines = (REPO / "etc" / "coopd.toml").read_text().splitlines()
    at = next(i for i, line in enumerate(lines) if line.startswith("mavlink = "))
    start = max(i for i in range(at) if not lines[i].startswith("#")) + 1
    comment = " ".join(lines[start:at])
    return re.findall(r'"([^"\s]+)"', comment) + [tomllib.loads(lines[at])["mavlink"]]


def on_loopback(text: str, port: int, device: str) -> str:
    """The same form of connection string with its host, port or device moved onto this machine's
    loopback (or a pty), so an example from the docs can really connect in a test."""
    e = parse_connection(text)
    if e.kind == "serial":
        return text.replace(e.device, device, 1)
    m = re.fullmatch(r"([a-z]+:(?://)?)(.*):(\d+)", text)
    return f"{m[1]}{'[::1]' if ':' in e.host else '127.0.0.1'}:{port}"


def test_every_example_in_the_config_file_connects():
    examples = documented_examples()
    assert len(examples) >= 6 and any(e.startswith("/dev/") for e in examples), examples
    for text in examples:
        parse_config(f"[vehicle]\nmavlink = {text!r}")  # passes the check ...
        if ":" in parse_connection(text).host and not has_ipv6_loopback():
            continue  # an IPv6 example needs ::1 to connect here (test_ipv6_form_connects skips too)
        pty = PtyChannel()
        local = on_loopback(text, free_port(), pty.path)
        want = parse_connection(text)
        assert (parse_connection(local).kind, parse_connection(local).baud) == (want.kind, want.baud)
        if parse_connection(local).kind != "serial":
            pty.close()
            pty = None
        connects(local, pty)  # ... and the same form connects


def test_tcpin_keeps_the_fc_and_refuses_a_stranger():
    """A connection that carried the FC's heartbeat is kept: a later one is refused and counted."""
    port = free_port(kind=socket.SOCK_STREAM)
    fc = LoopbackFc(TcpChannel(socket.AF_INET, connect_to=("127.0.0.1", port)), system_id=FC_SYSTEM)
    link = VehicleLink(LinkConfig(connection=f"tcpin:127.0.0.1:{port}", source_system=3))
    link.start()
    stranger = None
    try:
        assert fc.run_until(lambda: link.state == "ok" and link.transport.confirmed, seconds=5.0)
        stranger = socket.create_connection(("127.0.0.1", port), timeout=1.0)
        refused = lambda: link.transport.counters["connections_refused"] == 1  # noqa: E731
        assert fc.run_until(refused, seconds=5.0)
        stranger.settimeout(2.0)
        assert stranger.recv(100) == b""  # closed at once
        before = len(fc.messages("HEARTBEAT"))
        served = lambda: len(fc.messages("HEARTBEAT")) >= before + 2  # noqa: E731
        assert fc.run_until(served, seconds=5.0)  # the FC is still served
        assert link.state == "ok"
    finally:
        if stranger is not None:
            stranger.close()
        link.stop()
        fc.close()


def test_tcpin_replaces_a_silent_connection():
    """A stranger who connects first and says nothing does not hold the port: the FC's later
    connection replaces it."""
    port = free_port(kind=socket.SOCK_STREAM)
    link = VehicleLink(LinkConfig(connection=f"tcpin:127.0.0.1:{port}", source_system=3))
    link.start()
    squatter = fc = None
    try:
        deadline = time.monotonic() + 5.0
        while squatter is None and time.monotonic() < deadline:
            try:
                squatter = socket.create_connection(("127.0.0.1", port), timeout=1.0)
            except OSError:
                time.sleep(0.05)
        assert squatter is not None
        assert wait_until(lambda: link.transport.counters["connections"] == 1, 5.0)
        fc = LoopbackFc(TcpChannel(socket.AF_INET, connect_to=("127.0.0.1", port)), system_id=FC_SYSTEM)
        assert fc.run_until(lambda: link.state == "ok", seconds=5.0)
        assert link.transport.counters["connections_replaced"] == 1
    finally:
        for s in (squatter, fc):
            if s is not None:
                s.close()
        link.stop()

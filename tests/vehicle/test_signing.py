"""MAVLink 2 signing on the FC link: the key file, signed traffic both ways with a loopback FC,
unsigned or wrongly signed FC traffic refused and told, replays and forged timestamps refused."""

import os
import socket

import pytest
from pymavlink.dialects.v20 import common as mav

from coopd.vehicle.link import LinkConfig, VehicleLink
from coopd.vehicle.signing import StreamSigning, read_signing_key, signing_timestamp
from tests.loopback_fc import LoopbackFc, UdpChannel, free_port

KEY = bytes(range(32))
OTHER_KEY = bytes(range(1, 33))


def test_key_file(tmp_path):
    good = tmp_path / "key"
    good.write_text("  " + KEY.hex().upper() + "\n")
    assert read_signing_key(str(good)) == KEY
    for bad in ("abc", KEY.hex() + "00", "zz" * 32, "x" * 5000):
        (tmp_path / "bad").write_text(bad)
        with pytest.raises(ValueError, match="64 hexadecimal"):
            read_signing_key(str(tmp_path / "bad"))
    with pytest.raises(OSError):
        read_signing_key(str(tmp_path / "missing"))


class Wire:
    """A pymavlink output that keeps each packed message."""

    def __init__(self):
        self.packets = []

    def write(self, buf):
        self.packets.append(bytes(buf))


def signed_sender(key: bytes, system: int = 1, timestamp: int | None = None):
    wire = Wire()
    sender = mav.MAVLink(wire, srcSystem=system, srcComponent=1)
    sender.signing.secret_key, sender.signing.sign_outgoing = key, True
    sender.signing.timestamp = signing_timestamp(1.8e9) if timestamp is None else timestamp
    return sender, wire


def heartbeat(sender):
    sender.send(sender.heartbeat_encode(mav.MAV_TYPE_QUADROTOR, mav.MAV_AUTOPILOT_PX4, 0, 0, 4))


def receiver():
    r = mav.MAVLink(None, srcSystem=3, srcComponent=191)
    r.robust_parsing = True
    return r, StreamSigning(r, KEY)


def accepted(r, packet: bytes) -> bool:
    return [m.get_type() for m in r.parse_buffer(packet) or []] == ["HEARTBEAT"]


def test_replay_and_forged_future_timestamps_are_refused():
    r, signing = receiver()
    fc, wire = signed_sender(KEY)
    heartbeat(fc)
    heartbeat(fc)
    assert accepted(r, wire.packets[0]) and accepted(r, wire.packets[1])
    assert not accepted(r, wire.packets[0])  # replayed
    # a forged packet under the FC's ids with a far-future timestamp and no key: refused, and it does
    # not move the FC's stream (pymavlink's own check would, locking the FC out)
    forger, forged = signed_sender(OTHER_KEY, timestamp=signing_timestamp(4e9))
    heartbeat(forger)
    assert not accepted(r, forged.packets[0])
    heartbeat(fc)
    assert accepted(r, wire.packets[2])
    # a recording of another stream from more than a minute ago: refused
    old, old_wire = signed_sender(KEY, system=9, timestamp=signing_timestamp(1.8e9) - 61 * 100_000)
    heartbeat(old)
    assert not accepted(r, old_wire.packets[0])
    assert signing.counters()["signed_ok"] == 3 and signing.counters()["signature_bad"] == 3


def test_stream_table_is_bounded():
    r, signing = receiver()
    for system in range(1, 201):
        s, wire = signed_sender(KEY, system=system)
        heartbeat(s)
        assert accepted(r, wire.packets[0])
    assert len(signing.streams) == 64


def run_link(fc_key, link_key=KEY):
    port = free_port()
    fc = LoopbackFc(UdpChannel(socket.AF_INET, send_to=("127.0.0.1", port)), system_id=1, signing_key=fc_key)
    link = VehicleLink(LinkConfig(connection=f"udpin:127.0.0.1:{port}", source_system=1, target_system=1,
                                  signing_key=link_key))
    link.start()
    return fc, link


def test_signed_link_both_ways():
    fc, link = run_link(KEY)
    try:
        ours = lambda: [m for m in fc.messages("HEARTBEAT") if m.get_srcComponent() == 191]  # noqa: E731
        assert fc.run_until(lambda: link.state == "ok" and ours(), seconds=5.0), link.status()
        assert all(m._signed for m in ours())  # the FC verified our signatures (else it drops them)
        status = link.status()
        assert status["signing"] and status["counters"]["signing_signed_ok"] > 0
    finally:
        link.stop()
        fc.close()


@pytest.mark.parametrize(
    "fc_key, counter", [(None, "signing_unsigned_rejected"), (OTHER_KEY, "signing_signature_bad")]
)
def test_unsigned_or_wrongly_signed_fc_is_refused_and_told(fc_key, counter):
    fc, link = run_link(fc_key)
    try:
        told = lambda: link.status()["reason"] == "signature_rejected"  # noqa: E731
        assert fc.run_until(told, seconds=5.0), link.status()
        status = link.status()
        assert status["link"] == "connecting" and status["counters"][counter] > 0
        assert "vehicle.signing_key_file" in status["reason_detail"]
    finally:
        link.stop()
        fc.close()


def test_signing_is_off_by_default():
    link = VehicleLink(LinkConfig(connection=f"udpin:127.0.0.1:{free_port()}"))
    assert link.signing is None and link.mav.signing.secret_key is None and not link.status()["signing"]
    with pytest.raises(ValueError):
        LinkConfig(signing_key=os.urandom(16))

"""Why the link is not up, told to the operator: a system-id mismatch (vehicle.id != the FC's system
id) logged once with both ids and the message count and shown in the link's status, and the other
reasons (nothing received, port missing, bytes that are not MAVLink)."""

import logging
import re
import socket

import pytest
from sim_helpers import wait_until

from coopd.vehicle.link import MISMATCH_LOG_AFTER_S, LinkConfig, VehicleLink
from tests.loopback_fc import LoopbackFc, UdpChannel, free_port


def udp_link(port: int, vehicle_id: int = 1) -> VehicleLink:
    return VehicleLink(LinkConfig(connection=f"udpin:127.0.0.1:{port}", source_system=vehicle_id,
                                  target_system=vehicle_id))


def mismatch_lines(caplog) -> list[str]:
    return [r.getMessage() for r in caplog.records if "autopilot system" in r.getMessage()]


def test_system_id_mismatch_is_shown_within_5_s_and_logged_once(caplog):
    caplog.set_level(logging.INFO, logger="coopd.vehicle")
    port = free_port()
    link = udp_link(port, vehicle_id=1)
    fc = LoopbackFc(UdpChannel(socket.AF_INET, send_to=("127.0.0.1", port)), system_id=7)
    link.start()
    try:
        shown = lambda: link.status()["reason"] == "system_id_mismatch"  # noqa: E731
        assert fc.run_until(shown, seconds=5.0), link.status()
        status = link.status()
        detail = status["reason_detail"]
        assert status["link"] == "connecting"
        assert "expecting system 1" in detail and "autopilot system 7" in detail
        # the log line: once, after MISMATCH_LOG_AFTER_S, with both ids and how many messages were ignored
        assert fc.run_until(lambda: mismatch_lines(caplog), seconds=MISMATCH_LOG_AFTER_S + 3.0)
        fc.run_until(lambda: False, seconds=2.0)  # more heartbeats from system 7: no second line
        [line] = mismatch_lines(caplog)
        ignored = int(re.search(r"\((\d+) messages from it ignored\)", line)[1])
        assert "system 1 (vehicle.id)" in line and "vehicle.id = 7" in line and ignored >= 10
        assert link.counters["rx_foreign"] >= ignored
        # the right FC appears on the link: up, no reason
        right = LoopbackFc(UdpChannel(socket.AF_INET, send_to=("127.0.0.1", port)), system_id=1)
        try:
            assert right.run_until(lambda: link.state == "ok", seconds=5.0)
            assert link.status()["reason"] is None and link.status()["reason_detail"] is None
        finally:
            right.close()
    finally:
        link.stop()
        fc.close()


@pytest.fixture
def shared_link():
    """Our link (vehicle 1) started on a UDP port that two autopilots send to: ours (1) and another (2)."""
    port = free_port()
    link = udp_link(port, vehicle_id=1)
    ours = LoopbackFc(UdpChannel(socket.AF_INET, send_to=("127.0.0.1", port)), system_id=1)
    other = LoopbackFc(UdpChannel(socket.AF_INET, send_to=("127.0.0.1", port)), system_id=2)
    link.start()
    try:
        yield link, ours, other
    finally:
        link.stop()
        ours.close()
        other.close()


def test_a_second_vehicle_on_a_shared_link_is_no_mismatch(shared_link):
    """Through a router or radio several autopilots share a link: while ours talks, others are fine."""
    link, ours, other = shared_link
    assert ours.run_until(lambda: link.state == "ok", seconds=5.0, send=lambda _: other.heartbeat())
    ours.run_until(lambda: False, seconds=MISMATCH_LOG_AFTER_S + 0.5, send=lambda _: other.heartbeat())
    assert link.counters["rx_foreign"] > 0 and link.status()["reason"] is None


def test_another_autopilot_after_ours_went_silent_is_no_mismatch(shared_link):
    """Ours spoke, so vehicle.id is right: when it goes silent on a shared link, the link is lost,
    not mismatched."""
    link, ours, other = shared_link
    assert ours.run_until(lambda: link.state == "ok", seconds=5.0)
    lost = lambda: link.state == "lost"  # noqa: E731
    assert other.run_until(lost, seconds=5.0)
    other.run_until(lambda: False, seconds=MISMATCH_LOG_AFTER_S + 0.5)
    assert link.status()["reason"] == "no_traffic" and link.counters["rx_foreign"] > 0


def test_other_reasons():
    port = free_port()
    link = udp_link(port)
    link.start()
    try:
        assert wait_until(lambda: link.status()["reason"] == "no_traffic", 3.0)
        assert f"nothing received on udpin:127.0.0.1:{port}" == link.status()["reason_detail"]
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            for _ in range(3):
                s.sendto(b"\x00not mavlink at all" * 4, ("127.0.0.1", port))
            assert wait_until(lambda: link.status()["reason"] == "no_valid_mavlink", 3.0)
        assert "no valid MAVLink" in link.status()["reason_detail"]
    finally:
        link.stop()
    missing = VehicleLink(LinkConfig(connection="/dev/coopd-no-such-tty,57600"))
    missing.start()
    try:
        assert wait_until(lambda: missing.status()["reason_detail"].startswith("cannot open /dev/"), 3.0)
        assert missing.status()["reason"] == "transport_unavailable"
    finally:
        missing.stop()

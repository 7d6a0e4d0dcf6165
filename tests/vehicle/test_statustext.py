"""STATUSTEXT back to the FC/GCS: the rate limiter's rules, and texts and HEARTBEAT system_status
arriving at a loopback FC as MAVLink with their severities."""

import socket
import time

import pytest
from pymavlink.dialects.v20 import common as mav

from coopd.vehicle.link import LinkConfig, VehicleLink
from coopd.vehicle.statustext import MAX_TEXT, StatusTextLimiter
from tests.loopback_fc import LoopbackFc, UdpChannel, free_port

W = mav.MAV_SEVERITY_WARNING


def test_burst_then_rate():
    limiter = StatusTextLimiter(burst=3, per_s=0.5, repeat_s=0.0, queue=100)
    admitted = [limiter.push(W, f"event {i}", now=10.0) for i in range(5)]
    assert admitted == [True, True, True, False, False]
    assert not limiter.push(W, "event 5", now=11.0)  # half a token back
    assert limiter.push(W, "event 6", now=12.0)  # one token after 2 s
    assert limiter.counters == {"admitted": 4, "rate_limited": 3, "repeats": 0, "queue_full": 0}
    assert [t for _, t in limiter.take()] == [b"event 0", b"event 1", b"event 2", b"event 6"]
    assert limiter.take() == []


def test_the_same_text_once_per_window_and_a_bounded_queue():
    limiter = StatusTextLimiter(burst=100, per_s=100.0, repeat_s=10.0, queue=2)
    assert limiter.push(W, "camera stalled", now=0.0)
    assert not limiter.push(W, "camera stalled", now=5.0)
    assert limiter.push(W, "other", now=5.0)
    assert not limiter.push(W, "third", now=5.0)  # queue of 2 full: refused, counted
    assert limiter.counters["repeats"] == 1 and limiter.counters["queue_full"] == 1
    limiter.take()
    assert limiter.push(W, "camera stalled", now=10.5)


def test_texts_are_cut_to_one_statustext_and_severities_checked():
    limiter = StatusTextLimiter()
    limiter.push(mav.MAV_SEVERITY_INFO, "é" + "x" * 80, now=0.0)
    [(severity, text)] = limiter.take()
    assert severity == mav.MAV_SEVERITY_INFO and len(text) == MAX_TEXT and text.startswith(b"?x")
    with pytest.raises(ValueError):
        limiter.push(99, "x", now=0.0)


def test_statustext_and_system_status_reach_the_fc():
    port = free_port()
    fc = LoopbackFc(UdpChannel(socket.AF_INET, send_to=("127.0.0.1", port)), system_id=1)
    link = VehicleLink(LinkConfig(connection=f"udpin:127.0.0.1:{port}", source_system=1, target_system=1,
                                  heartbeat_period_s=0.2))
    link.start()
    try:
        assert fc.run_until(lambda: link.state == "ok", seconds=5.0)
        assert link.statustext(mav.MAV_SEVERITY_WARNING, "coopd: camera stalled")
        assert not link.statustext(mav.MAV_SEVERITY_WARNING, "coopd: camera stalled")  # repeat
        link.system_status = mav.MAV_STATE_CRITICAL
        texts = lambda: [m for m in fc.messages("STATUSTEXT") if m.get_srcSystem() == 1]  # noqa: E731
        critical = lambda: [m for m in fc.messages("HEARTBEAT")  # noqa: E731
                            if m.get_srcComponent() == 191 and m.system_status == mav.MAV_STATE_CRITICAL]
        assert fc.run_until(lambda: texts() and critical(), seconds=5.0)
        [m] = texts()
        assert m.severity == mav.MAV_SEVERITY_WARNING and m.text == "coopd: camera stalled"
        assert m.get_srcComponent() == mav.MAV_COMP_ID_ONBOARD_COMPUTER
        status = link.status()["counters"]
        assert status["statustext_sent"] == 1 and status["statustext_repeats"] == 1
    finally:
        link.stop()
        fc.close()


def test_texts_pushed_before_the_fc_is_heard_wait_for_it():
    """An event before the FC spoke (camera frames before the first odometry) is not sent to nobody:
    it waits in the bounded queue and reaches the FC once the link is up."""
    port = free_port()
    link = VehicleLink(LinkConfig(connection=f"udpin:127.0.0.1:{port}", source_system=1, target_system=1,
                                  heartbeat_period_s=0.2))
    link.start()
    fc = None
    try:
        assert link.statustext(mav.MAV_SEVERITY_NOTICE, "coopd: camera frames ok")
        time.sleep(0.3)  # the link thread runs its timers meanwhile, with nobody to send to
        assert link.status()["counters"].get("statustext_sent", 0) == 0
        fc = LoopbackFc(UdpChannel(socket.AF_INET, send_to=("127.0.0.1", port)), system_id=1)
        texts = lambda: [m for m in fc.messages("STATUSTEXT") if m.get_srcSystem() == 1]  # noqa: E731
        assert fc.run_until(lambda: texts(), seconds=5.0)
        assert [m.text for m in texts()] == ["coopd: camera frames ok"]
    finally:
        link.stop()
        if fc is not None:
            fc.close()

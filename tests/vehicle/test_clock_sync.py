"""FC clock estimation from TIMESYNC round trips (skew included) and the SYSTEM_TIME fallback."""

import numpy as np
import pytest

from coopd.vehicle.clock import ClockSync

NS = 1_000_000_000


def feed(sync, offset, rate, n, rng, start=100.0, period=0.2, max_rtt=0.004):
    """Simulated round trips: request at local t, FC stamps at the midpoint, reply after rtt."""
    for k in range(n):
        t = start + k * period
        rtt = rng.uniform(0.0005, max_rtt)
        ts1 = sync.new_request(int(t * NS))
        tc1 = int((offset + rate * (t + rtt / 2)) * NS)
        sync.on_timesync_reply(tc1, ts1, int((t + rtt) * NS))


@pytest.mark.parametrize("rate", [1.0, 1.00005, 2.0])
def test_converges_to_offset_and_rate(rate):
    sync = ClockSync()
    feed(sync, offset=-95.0, rate=rate, n=24, rng=np.random.default_rng(1))
    est = sync.estimate()
    assert est.rate == pytest.approx(rate, rel=2e-3) and est.source == "timesync"
    for local in (101.0, 104.0):
        assert abs(est.fc_time(local) - (-95.0 + rate * local)) < 0.003
    assert est.uncertainty_s < 0.01
    assert est.local_time(est.fc_time(103.0)) == pytest.approx(103.0)


def test_unmatched_and_slow_replies_are_refused_and_counted():
    sync = ClockSync(max_rtt_s=0.1)
    assert not sync.on_timesync_reply(5 * NS, 12345, 13 * NS)
    ts1 = sync.new_request(10 * NS)
    assert not sync.on_timesync_reply(5 * NS, ts1, int(10.5 * NS))
    assert sync.counters["timesync_unmatched"] == 1 and sync.counters["timesync_rtt_rejected"] == 1
    assert sync.estimate() is None


def test_fc_reboot_restarts_the_estimate():
    sync = ClockSync()
    rng = np.random.default_rng(2)
    feed(sync, offset=500.0, rate=1.0, n=10, rng=rng)
    feed(sync, offset=-100.0, rate=1.0, n=10, rng=rng, start=110.0)  # FC clock back near zero
    assert sync.counters["fc_clock_resets"] == 1
    assert abs(sync.estimate().fc_time(111.0) - 11.0) < 0.005


def test_system_time_only_while_timesync_is_silent():
    sync = ClockSync()
    assert sync.on_system_time(5_000, 10.0)  # no TIMESYNC ever: fallback in use
    assert sync.estimate().source == "system_time"
    assert sync.estimate().uncertainty_s >= sync.system_time_uncertainty_s
    feed(sync, offset=-5.0, rate=1.0, n=3, rng=np.random.default_rng(3), start=10.5)
    assert sync.estimate().source == "timesync"
    assert not sync.on_system_time(6_000, 11.5)  # TIMESYNC fresh: SYSTEM_TIME ignored


def test_a_clock_step_is_followed_within_a_few_samples():
    sync = ClockSync()
    rng = np.random.default_rng(4)
    feed(sync, offset=-95.0, rate=1.0, n=20, rng=rng, period=1.0)
    feed(sync, offset=-95.3, rate=1.0, n=4, rng=rng, start=120.0, period=1.0)  # FC clock 0.3 s behind now
    assert sync.counters["fc_clock_steps"] == 1 and sync.counters["fc_clock_resets"] == 0
    assert abs(sync.estimate().fc_time(124.0) - (-95.3 + 124.0)) < 0.005

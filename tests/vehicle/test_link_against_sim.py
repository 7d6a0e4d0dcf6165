"""The MAVLink link against firmware_sim for real: connect, odometry, clock, loss, reboot, hostile input."""

import math
import os
import socket
import time

import numpy as np
import pytest
from pymavlink.dialects.v20 import common as mav
from sim_helpers import pose_errors, wait_until

from coopd.vehicle import LinkConfig, VehicleLink
from firmware_sim.odometry import NoiseConfig
from firmware_sim.simulation import Simulation
from firmware_sim.worlds import build_world

NOISE = NoiseConfig(
    pos_sigma_m=0.01,
    vel_sigma_m_s=0.02,
    att_sigma_rad=0.003,
    drift_xy_m_s=0.0,
    drift_z_m_s=0.0,
    drift_yaw_rad_s=0.0,
)


@pytest.fixture(scope="module")
def world():
    return build_world("small_house", 0)


@pytest.fixture
def rig(world, udp_port):
    """A running emulator (speed 4, no camera) and a started link on our own port; both torn down."""
    made = []

    def make(route=None, noise=NOISE, speed=4.0, before_start=None, **link_kw):
        sim = Simulation(
            world, 1, seed=3, speed=speed, noise=noise, camera=None, mavlink_base_port=udp_port, route=route
        )
        if before_start is not None:
            before_start(sim)
        link = VehicleLink(LinkConfig(connection=f"udpin:127.0.0.1:{udp_port}", **link_kw))
        made.append((sim, link))
        link.start()
        sim.start()
        return sim, link

    yield make
    for sim, link in made:
        link.stop()
        sim.stop()


def test_connects_streams_and_poses_match_the_truth(rig):
    sim, link = rig(route="builtin")
    assert wait_until(lambda: not link.odometry_stale(), 5.0), link.status()
    assert wait_until(lambda: sim.time > 20.0, 15.0)  # takeoff and the first legs of the route
    fc = sim.vehicle(0).link.stats
    assert fc["peer_heartbeats"] >= 1
    assert fc[f"cmd_{mav.MAV_CMD_SET_MESSAGE_INTERVAL}_{mav.MAV_RESULT_ACCEPTED}"] >= 4
    st = link.status()
    assert st["link"] == "ok" and st["target_system"] == 1 and not st["odometry_stale"]
    pos_err, att_err = pose_errors(link, sim)
    moved = np.ptp(np.array([s.position for s in link.poses.samples()]), axis=0).max()
    print(
        f"poses {len(pos_err)}, moved {moved:.1f} m; position error rms {np.sqrt(np.mean(pos_err**2)):.4f} m "
        f"max {pos_err.max():.4f} m; attitude error max {att_err.max():.3f} deg"
    )
    assert len(pos_err) > 300 and moved > 2.0
    # Noise sigma 0.01 m per axis on each sample and on the origin sample: |err| ~ 0.024 m rms.
    assert np.sqrt(np.mean(pos_err**2)) < 0.04 and pos_err.max() < 0.1
    assert att_err.max() < 1.5  # 0.003 rad sigma per axis, plus the 25 Hz truth log's interpolation


def test_clock_offset_converges_to_the_emulators_clock(rig):
    sim, link = rig(speed=2.0)
    assert wait_until(lambda: (e := link.clock.estimate()) is not None and e.samples >= 12, 10.0)
    errors = []
    for _ in range(40):
        with sim.lock:  # sim.time only moves between physics steps, which hold this lock
            errors.append(link.clock.estimate().fc_time(time.monotonic()) - sim.time)
        time.sleep(0.02)
    errors = np.abs(errors)
    est = link.clock.estimate()
    print(
        f"clock: rate {est.rate:.5f} (emulator speed 2), uncertainty {est.uncertainty_s * 1e3:.2f} ms, "
        f"|fc_pred - sim.time| median {np.median(errors) * 1e3:.2f} ms max {errors.max() * 1e3:.2f} ms"
    )
    assert est.source == "timesync" and abs(est.rate - 2.0) < 0.05
    # The emulator steps in batches of up to 25 x 4 ms against the wall clock: a few ms of jitter.
    assert np.median(errors) < 0.02 and errors.max() < 0.25


def test_link_loss_marks_stale_and_recovers_by_itself(rig):
    sim, link = rig(link_timeout_s=1.0, odometry_timeout_s=0.3)
    assert wait_until(lambda: not link.odometry_stale(), 5.0)
    with sim.lock:  # the emulator freezes: no telemetry at all
        t0 = time.monotonic()
        assert wait_until(link.odometry_stale, 1.0)
        stale_after = time.monotonic() - t0
        assert wait_until(lambda: link.status()["link"] == "lost", 2.0)
        lost_after = time.monotonic() - t0
        newest = link.poses.latest().t_fc
    t1 = time.monotonic()
    assert wait_until(lambda: not link.odometry_stale() and link.status()["link"] == "ok", 3.0)
    print(
        f"stale after {stale_after:.2f} s, lost after {lost_after:.2f} s, "
        f"back after {time.monotonic() - t1:.2f} s"
    )
    assert stale_after < 0.3 + 0.2 and lost_after < 1.0 + 0.3
    assert link.poses.latest().t_fc > newest and link.counters["link_losses"] == 1


def test_fc_reboot_restarts_time_base_and_mapping_resumes(rig):
    sim, link = rig(link_timeout_s=1.0)
    assert wait_until(lambda: not link.odometry_stale() and sim.time > 3.0, 5.0)
    sim.stop()  # the FC goes away: port closed, nothing sent
    assert wait_until(lambda: link.status()["link"] == "lost", 2.5)
    port = int(link.config.connection.rsplit(":", 1)[1])
    sim2 = Simulation(sim.world, 1, seed=4, speed=4.0, noise=NOISE, camera=None, mavlink_base_port=port)
    try:
        sim2.start()
        assert wait_until(lambda: link.status()["link"] == "ok" and not link.odometry_stale(), 5.0)
        assert wait_until(
            lambda: link.clock.estimate() is not None and link.clock.estimate().samples >= 12, 8.0
        )
        assert link.counters["fc_reboots"] == 1
        assert link.poses.span()[0] < 2.0  # the buffer holds the new FC's time base only
        with sim2.lock:
            assert abs(link.clock.estimate().fc_time(time.monotonic()) - sim2.time) < 0.1
    finally:
        sim2.stop()


def test_falls_back_to_local_position_and_attitude_quaternion(rig):
    def without_odometry(sim):
        fc_link = sim.vehicle(0).link
        del fc_link.producers[mav.MAVLINK_MSG_ID_ODOMETRY]  # an FC that cannot send ODOMETRY
        fc_link.intervals[mav.MAVLINK_MSG_ID_ODOMETRY] = 0.0

    sim, link = rig(route="builtin", before_start=without_odometry)
    assert wait_until(lambda: not link.odometry_stale() and sim.time > 12.0, 10.0), link.status()
    assert link.counters["fallback_samples"] > 100
    pos_err, att_err = pose_errors(link, sim)
    assert len(pos_err) > 100 and np.sqrt(np.mean(pos_err**2)) < 0.04 and att_err.max() < 1.5


def hostile_datagrams(rng, n):
    """Random bytes, MAVLink frames with broken CRCs, truncations, absurd lengths, foreign systems."""
    enc = mav.MAVLink(None, 200, 1)
    good = enc.odometry_encode(
        1, 1, 12, 1e9, math.nan, 0, [9.0, 0, 0, 0], 0, 0, 0, 0, 0, 0, [0.0] * 21, [0.0] * 21, 0, 0, 0
    ).pack(enc)
    fake_fc = mav.MAVLink(None, 1, 1)  # claims to be the FC: NaN/absurd odometry must be rejected
    nan_odo = fake_fc.odometry_encode(
        10**12, 1, 12, math.nan, 0, 0, [1.0, 0, 0, 0], 0, 0, 0, 0, 0, 0, [0.0] * 21, [0.0] * 21, 0, 0, 0
    ).pack(fake_fc)
    for k in range(n):
        kind = k % 6
        if kind == 0:
            yield rng.bytes(int(rng.integers(1, 1400)))
        elif kind == 1:
            b = bytearray(good)
            b[-1] ^= 0xFF
            yield bytes(b)
        elif kind == 2:
            yield good[: int(rng.integers(1, len(good)))]
        elif kind == 3:
            yield bytes([0xFD, 0xFF, 0, 0, 0, 1, 1]) + rng.bytes(40)
        elif kind == 4:
            yield good
        else:
            yield nan_odo


def test_hostile_udp_input_is_counted_and_never_stops_the_link(rig):
    sim, link = rig()
    assert wait_until(lambda: not link.odometry_stale(), 5.0)
    port = int(link.config.connection.rsplit(":", 1)[1])
    rng = np.random.default_rng(int.from_bytes(os.urandom(4), "little"))
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        deadline = time.monotonic() + 5.0
        for k, d in enumerate(hostile_datagrams(rng, 3000)):
            s.sendto(d, ("127.0.0.1", port))
            if k % 100 == 99:
                time.sleep(0.01)
            if time.monotonic() > deadline:
                break
    # The flood may crowd FC datagrams out of the socket buffer for a moment: allow it to settle.
    assert wait_until(lambda: link.status()["link"] == "ok" and not link.odometry_stale(), 2.0)
    st = link.status()
    c = st["counters"]
    print({k: v for k, v in c.items() if "bad" in k or "foreign" in k or "rejected" in k or "error" in k})
    assert c["rx_bad_data"] > 100 and c["rx_foreign"] > 100
    assert c.get("odometry_rejected_not_finite", 0) + c.get("odometry_rejected_absurd", 0) > 0
    assert st["link"] == "ok" and not st["odometry_stale"] and c.get("loop_errors", 0) == 0
    assert st["max_loop_s"] < 0.25, st["max_loop_s"]  # reads are bounded: the flood never stalls the loop
    assert np.all(np.isfinite(link.poses.latest().position))
    assert link.transport.peer[1] == sim.vehicle(0).link.bound_port  # replies still go to the FC


def test_each_link_follows_its_own_vehicle(world, udp_port):
    """Two vehicles, two links: each locks onto its own system id and its own start frame."""
    sim = Simulation(world, 2, seed=5, speed=4.0, noise=NOISE, camera=None, mavlink_base_port=udp_port)
    links = [VehicleLink(LinkConfig(connection=f"udpin:127.0.0.1:{udp_port + i}")) for i in range(2)]
    for lk in links:
        lk.start()
    sim.start()
    try:
        assert wait_until(lambda: all(not lk.odometry_stale() for lk in links), 5.0)
        assert wait_until(lambda: all(len(lk.poses) > 90 for lk in links), 5.0)
        for i, lk in enumerate(links):
            assert lk.target_system == i + 1
            pos_err, _ = pose_errors(lk, sim, i)
            assert len(pos_err) >= 30 and pos_err.max() < 0.1
    finally:
        for lk in links:
            lk.stop()
        sim.stop()


def test_system_time_stands_in_when_timesync_is_unanswered(rig):
    def deaf_to_timesync(sim):
        sim.vehicle(0).link._on_timesync = lambda m: None  # an FC that never answers TIMESYNC

    sim, link = rig(speed=2.0, before_start=deaf_to_timesync)
    # SYSTEM_TIME comes at 1 Hz of FC time; the rate is fitted once samples span 1 s of our time.
    assert wait_until(lambda: (e := link.clock.estimate()) is not None and e.samples >= 6, 10), link.status()
    est = link.clock.estimate()
    with sim.lock:
        err = est.fc_time(time.monotonic()) - sim.time
    print(
        f"SYSTEM_TIME fallback: rate {est.rate:.4f}, error {err * 1e3:.1f} ms, "
        f"claimed {est.uncertainty_s * 1e3:.1f} ms"
    )
    assert est.source == "system_time" and abs(est.rate - 2.0) < 0.1 and abs(err) < 0.1

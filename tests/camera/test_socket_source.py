"""Camera socket client against scripted drivers: frames, hostile input, stalls, restarts, newest wins."""

import struct
import time
import tracemalloc

import msgpack
import numpy as np
import pytest
from fake_driver import FakeDriver, depth_of, frame_bytes, header, wait_until

from coopd.camera import SocketDepthSource, SocketSourceConfig


@pytest.fixture
def sock_path(tmp_path):
    return str(tmp_path / "cam.sock")


@pytest.fixture
def make_source(sock_path):
    made = []

    def make(fc=None, host_to_fc=None, **kw):
        kw.setdefault("stall_timeout_s", 0.4)
        kw.setdefault("backoff_s", (0.02, 0.2))
        src = SocketDepthSource(SocketSourceConfig(sock_path, **kw), fc=fc, host_to_fc=host_to_fc)
        made.append(src)
        src.start()
        return src

    yield make
    for src in made:
        t0 = time.monotonic()
        src.stop()
        assert time.monotonic() - t0 < 1.5, "stop() must be prompt"


def send_frames(seqs, then=None):
    """Script: send frames with these seqs (t_us = 1000 * (seq + 1)), then call `then` or wait to stop."""

    def script(conn, index, stopping):
        for s in seqs:
            conn.sendall(frame_bytes(header(seq=s, t_us=1000 * (s + 1))))
        if then is not None:
            then(conn, index, stopping)
        else:
            stopping.wait(5)

    return script


def test_receives_valid_frames_exactly(sock_path, make_source):
    drv = FakeDriver(sock_path, send_frames([0]))
    try:
        src = make_source()
        f = src.slot.take(timeout=3.0)
        assert f is not None and f.seq == 0 and f.t_fc == pytest.approx(0.001)
        assert f.depth.dtype == np.uint16 and np.array_equal(f.depth, depth_of(header(seq=0)))
        assert f.intrinsics.width == 8 and f.intrinsics.depth_scale == 0.001
        assert src.status()["connected"] and src.counters["frames"] == 1
    finally:
        drv.close()


def test_newest_wins_and_drops_are_counted(sock_path, make_source):
    drv = FakeDriver(sock_path, send_frames(range(6)))
    try:
        src = make_source()
        assert wait_until(lambda: src.counters["frames"] == 6, 3.0)
        f = src.slot.take()
        assert f.seq == 5 and src.slot.dropped == 5 and src.slot.take() is None
    finally:
        drv.close()


def hostile(payload_for_connection):
    """Script: connection 0 gets hostile bytes, later connections get one good frame."""

    def script(conn, index, stopping):
        if index == 0:
            conn.sendall(payload_for_connection)
            stopping.wait(5)  # keep the socket open: the client must give up by itself
        else:
            conn.sendall(frame_bytes(header(seq=100 + index, t_us=10**6 + index)))
            stopping.wait(5)

    return script


def packed(d):
    h = msgpack.packb(d)
    return struct.pack("<I", len(h)) + h


HOSTILE = {
    "zero_header_length": (struct.pack("<I", 0), "protocol_bad_header_length"),
    "huge_header_length": (struct.pack("<I", 2**31) + b"x" * 64, "protocol_bad_header_length"),
    "garbage_header": (struct.pack("<I", 16) + b"\xc1" * 16, "protocol_bad_msgpack"),
    "not_a_map": (packed([1, 2, 3]), "protocol_bad_header"),
    "oversize_announcement": (packed(header(w=4096, h=4096, n=4096 * 4096 * 2)), "protocol_oversize"),
    "n_mismatch": (packed(header(n=10**9)), "protocol_bad_size"),
    "wrong_encoding": (packed(header(enc="rgb8")), "protocol_bad_encoding"),
    "nan_intrinsics": (packed(header(fx=float("nan"))), "protocol_bad_header"),
}


@pytest.mark.parametrize("case", sorted(HOSTILE))
def test_hostile_driver_is_dropped_counted_and_reconnected(sock_path, make_source, case):
    data, counter = HOSTILE[case]
    drv = FakeDriver(sock_path, hostile(data))
    try:
        tracemalloc.start()
        src = make_source(max_payload_bytes=1 << 20)
        f = src.slot.take(timeout=3.0)
        _, peak = tracemalloc.get_traced_memory()
        tracemalloc.stop()
        assert f is not None and f.seq >= 101, src.status()  # recovered on a fresh connection
        assert src.counters[counter] == 1 and src.counters["disconnect_protocol_error"] == 1
        assert peak < 4 << 20, f"peak allocation {peak} B: announcements must not be trusted"
    finally:
        drv.close()


def test_truncated_payload_then_eof_delivers_nothing(sock_path, make_source):
    def script(conn, index, stopping):
        if index == 0:
            conn.sendall(frame_bytes(header(seq=1, t_us=5000))[:-7])
            return  # close mid-payload
        conn.sendall(frame_bytes(header(seq=2, t_us=6000)))
        stopping.wait(5)

    drv = FakeDriver(sock_path, script)
    try:
        src = make_source()
        f = src.slot.take(timeout=3.0)
        assert f.seq == 2 and src.counters["frames"] == 1 and src.counters["disconnect_eof"] >= 1
    finally:
        drv.close()


def test_stalled_connection_is_abandoned_and_reconnected(sock_path, make_source):
    def script(conn, index, stopping):
        data = frame_bytes(header(seq=index, t_us=1000 + index))
        if index == 0:
            conn.sendall(data[:30])  # then silence, socket open
            stopping.wait(5)
            return
        conn.sendall(data)
        stopping.wait(5)

    drv = FakeDriver(sock_path, script)
    try:
        t0 = time.monotonic()
        src = make_source(stall_timeout_s=0.3)
        f = src.slot.take(timeout=3.0)
        assert f is not None and f.seq == 1
        assert src.counters["disconnect_stall"] == 1 and 0.3 <= time.monotonic() - t0 < 2.0
    finally:
        drv.close()


def test_driver_restart_reconnects_with_backoff(sock_path, make_source):
    src = make_source()
    time.sleep(0.3)  # nobody listening yet: connection attempts fail and back off
    assert src.counters["connect_failures"] >= 2 and not src.connected
    drv = FakeDriver(sock_path, send_frames([0]))
    assert src.slot.take(timeout=3.0) is not None
    drv.close()  # driver goes away
    assert wait_until(lambda: not src.connected, 2.0)
    drv = FakeDriver(sock_path, send_frames([0, 1]))  # restarted driver: sequence and clock restart
    try:
        assert wait_until(lambda: src.counters["frames"] >= 3, 3.0), src.status()
        assert src.counters["connects"] >= 2  # a connect may land in the dying listener's backlog
    finally:
        drv.close()


def test_non_increasing_timestamps_are_dropped_and_seq_gaps_counted(sock_path, make_source):
    def script(conn, index, stopping):
        for seq, t in ((0, 1000), (1, 1000), (2, 900), (5, 2000)):
            conn.sendall(frame_bytes(header(seq=seq, t_us=t)))
        stopping.wait(5)

    drv = FakeDriver(sock_path, script)
    try:
        src = make_source()
        assert wait_until(lambda: src.counters["frames"] == 2, 3.0)
        assert src.counters["dropped_timestamp_not_increasing"] == 2 and src.counters["seq_gaps"] == 1
    finally:
        drv.close()


def test_bad_configuration_is_refused():
    for kw in (
        {"address": ""},
        {"address": "/x", "max_payload_bytes": 0},
        {"address": "/x", "stall_timeout_s": 0},
    ):
        with pytest.raises(ValueError):
            SocketSourceConfig(**kw)


def test_a_byte_trickling_driver_is_abandoned(sock_path, make_source):
    def script(conn, index, stopping):
        data = frame_bytes(header(seq=index, t_us=1000 + index))
        if index == 0:
            for b in data[:200]:  # one byte every 50 ms: never a stall, never a frame
                if stopping.wait(0.05):
                    return
                conn.sendall(bytes([b]))
            return
        conn.sendall(data)
        stopping.wait(5)

    drv = FakeDriver(sock_path, script)
    try:
        src = make_source(stall_timeout_s=0.3, frame_timeout_s=0.5)
        f = src.slot.take(timeout=3.0)
        assert f is not None and f.seq == 1 and src.counters["disconnect_slow_frame"] == 1
    finally:
        drv.close()


class StubFcClock:
    """The vehicle link as the camera client sees it: the FC's clock now and its reboot count."""

    def __init__(self, now_s=None, epoch=0):
        self.now_s, self.epoch = now_s, epoch

    def fc_time_latest(self):
        return self.now_s

    def fc_epoch(self):
        return self.epoch


def test_a_frame_from_the_future_is_dropped_without_moving_the_reference(sock_path, make_source):
    """One frame stamped far after the FC's clock must not make every later frame 'old'."""

    def script(conn, index, stopping):
        for seq, t in ((0, 1000), (1, 2000), (2, 10**12), (3, 3000), (4, 4000)):
            conn.sendall(frame_bytes(header(seq=seq, t_us=t)))
        stopping.wait(5)

    drv = FakeDriver(sock_path, script)
    try:
        src = make_source(fc=StubFcClock(now_s=0.005))
        assert wait_until(lambda: src.counters["frames"] == 4, 3.0), src.status()
        assert src.counters["dropped_future_timestamp"] == 1
        assert src.counters["dropped_timestamp_not_increasing"] == 0
        f = src.slot.take()
        assert f.seq == 4 and f.t_fc == pytest.approx(0.004)
    finally:
        drv.close()


def test_an_fc_reboot_resets_the_time_reference_at_once(sock_path, make_source):
    """After the FC rebooted, the driver's first frame in the new (small) FC time is mapped."""
    fc = StubFcClock(now_s=20.0)

    def script(conn, index, stopping):
        for seq in range(3):
            conn.sendall(frame_bytes(header(seq=seq, t_us=(18 + seq) * 10**6)))
        stopping.wait(0.3)
        fc.now_s, fc.epoch = 0.6, 1  # the FC rebooted; the link saw it
        conn.sendall(frame_bytes(header(seq=3, t_us=500_000)))
        stopping.wait(5)

    drv = FakeDriver(sock_path, script)
    try:
        src = make_source(fc=fc)
        assert wait_until(lambda: src.counters["frames"] == 4, 3.0), src.status()
        assert src.counters["time_reference_resets_fc_reboot"] == 1
        assert src.slot.take().t_fc == pytest.approx(0.5)
    finally:
        drv.close()


def test_host_monotonic_stamps_are_converted_with_the_fc_clock_fit(sock_path, make_source):
    """Frames stamped with the host's monotonic clock come out in FC time; before the fit exists,
    from the host's future, or going back they are dropped and counted; an FC reboot does not
    reset a host-time reference; FC-stamped frames on the same connection still work."""
    fit = {"offset": None}
    fc = StubFcClock(now_s=None)

    def host_to_fc(local_s):
        return None if fit["offset"] is None else local_s + fit["offset"]

    def script(conn, index, stopping):
        now_us = fit["start_us"] = int(time.monotonic() * 1e6)
        conn.sendall(frame_bytes(header(seq=0, t_us=now_us, clock="monotonic")))  # no fit yet
        stopping.wait(0.3)
        fit["offset"], fc.epoch = -1000.0, 1  # the link fitted the clock (after an FC reboot)
        fc.now_s = time.monotonic() - 1000.0
        for seq, t in ((1, now_us + 100_000), (2, now_us + 60 * 10**6), (3, now_us + 50_000),
                       (4, now_us + 200_000)):
            conn.sendall(frame_bytes(header(seq=seq, t_us=t, clock="monotonic")))
        stopping.wait(0.3)
        conn.sendall(frame_bytes(header(seq=5, t_us=int(fc.now_s * 1e6), clock="fc")))
        stopping.wait(5)

    drv = FakeDriver(sock_path, script)
    try:
        src = make_source(fc=fc, host_to_fc=host_to_fc)
        assert wait_until(lambda: src.counters["frames"] == 2, 3.0), src.status()
        c = src.counters
        assert c["dropped_no_fc_clock"] == 1 and c["dropped_future_timestamp"] == 1, src.status()
        assert c["dropped_timestamp_not_increasing"] == 1 and c["time_reference_resets_fc_reboot"] == 0
        f = src.slot.take()
        assert f.seq == 4 and f.t_fc == pytest.approx(fit["start_us"] * 1e-6 + 0.2 - 1000.0, abs=1e-6)
        assert wait_until(lambda: src.counters["frames"] == 3, 3.0), src.status()
        assert c["time_reference_resets_clock_domain_changed"] == 1
        assert src.slot.take().t_fc == pytest.approx(fc.now_s, abs=1e-6)
    finally:
        drv.close()


def test_host_monotonic_stamps_without_a_converter_are_dropped(sock_path, make_source):
    def script(conn, index, stopping):
        conn.sendall(frame_bytes(header(seq=0, t_us=int(time.monotonic() * 1e6), clock="monotonic")))
        conn.sendall(frame_bytes(header(seq=1, t_us=1000)))
        stopping.wait(5)

    drv = FakeDriver(sock_path, script)
    try:
        src = make_source()
        assert wait_until(lambda: src.counters["frames"] == 1, 3.0), src.status()
        assert src.counters["dropped_no_fc_clock"] == 1 and src.slot.take().seq == 1
    finally:
        drv.close()


def test_stamps_that_stay_behind_the_reference_become_the_new_reference(sock_path, make_source):
    """Without an FC clock to judge by, one bad stamp costs at most relatch_after_s of frames."""

    def script(conn, index, stopping):
        conn.sendall(frame_bytes(header(seq=0, t_us=10**12)))  # latches the reference far ahead
        for k in range(1, 40):  # then a good stream at 20 Hz, for at most 2 s
            conn.sendall(frame_bytes(header(seq=k, t_us=10**6 + k * 50_000)))
            if stopping.wait(0.05):
                return
        stopping.wait(5)

    drv = FakeDriver(sock_path, script)
    try:
        src = make_source(relatch_after_s=0.3)
        assert wait_until(lambda: src.counters["frames"] >= 10, 3.0), src.status()
        assert src.counters["time_reference_resets_stamps_went_back"] == 1
        assert 3 <= src.counters["dropped_timestamp_not_increasing"] <= 10
        assert src.slot.take().t_fc < 3.0
    finally:
        drv.close()


ABSURD_BUT_WELL_FORMED = {  # inside the protocol's hard limits, yet no depth camera looks like this
    "fov_178_deg": {"fx": 0.2},
    "fov_0.04_deg": {"fx": 9e4, "fy": 9e4},
    "principal_point_left_of_image": {"cx": -60.0},
    "principal_point_below_image": {"cy": 90.0},
    "scale_6.5_cm_range": {"scale": 1e-6},
    "scale_59_km_range": {"scale": 0.9},
}


@pytest.mark.parametrize("case", sorted(ABSURD_BUT_WELL_FORMED))
def test_absurd_intrinsics_are_dropped_counted_and_logged_without_losing_the_connection(
    sock_path, make_source, case, caplog
):
    good = dict(w=64, h=48, fx=40.0, fy=40.0, cx=31.5, cy=23.5)
    bad = dict(good, **ABSURD_BUT_WELL_FORMED[case])

    def script(conn, index, stopping):
        for seq, fields in enumerate((bad, good, bad, good)):
            conn.sendall(frame_bytes(header(seq=seq, t_us=1000 * (seq + 1), **fields)))
        stopping.wait(5)

    drv = FakeDriver(sock_path, script)
    caplog.set_level("WARNING", logger="coopd.camera")
    try:
        src = make_source()
        assert wait_until(lambda: src.counters["frames"] == 2, 3.0), src.status()
        assert src.counters["dropped_implausible_intrinsics"] == 2 and src.counters["connects"] == 1
        assert src.slot.take().seq == 3
        lines = [r.getMessage() for r in caplog.records if "implausible intrinsics" in r.getMessage()]
        assert len(lines) == 1 and "frame 0 dropped" in lines[0], lines  # the 1st, then the 10th ...
        print(lines[0])
    finally:
        drv.close()


def test_a_failed_connect_says_what_to_check(tmp_path, caplog):
    """Missing directory, no driver yet, a driver that died (stale socket), wrong permissions."""
    import errno
    import socket

    from coopd.camera.socket_source import explain_connect_failure

    def failure(path):
        s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        try:
            s.connect(path)
        except OSError as e:
            return explain_connect_failure(path, e)
        finally:
            s.close()
        raise AssertionError("connected")

    assert "does not exist" in failure(str(tmp_path / "missing" / "cam.sock"))
    assert "is the camera driver running" in failure(str(tmp_path / "cam.sock"))
    stale = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    stale.bind(str(tmp_path / "stale.sock"))
    stale.close()  # the file stays, nobody listens
    assert "nobody listens" in failure(str(tmp_path / "stale.sock"))
    denied = OSError(errno.EACCES, "Permission denied")
    assert "group coopd" in explain_connect_failure(str(tmp_path / "cam.sock"), denied)
    caplog.set_level("WARNING", logger="coopd.camera")
    missing = str(tmp_path / "missing" / "cam.sock")
    src = SocketDepthSource(SocketSourceConfig(missing, backoff_s=(0.02, 0.05)))
    src.start()
    try:
        assert wait_until(lambda: src.counters["connect_failures"] >= 12, 3.0)
    finally:
        src.stop()
    lines = [r.getMessage() for r in caplog.records if "not reachable" in r.getMessage()]
    assert len(lines) == 2 and "does not exist" in lines[0] and "(10 failures)" in lines[1], lines

"""Version pinning: a forged huge version, an epoch that goes back or a counter that jumps is
refused and counted; a forgery within the bounds holds only until the real vehicle, told its
version was refused, publishes in a new epoch."""

import time

import pytest
import sharing_testmsg as tm
from sharing_support import failures, service, settings, wait_until

from coopd.sharing import mtp, versions
from coopd.sharing.transport import PeerLink

STEP = versions.MAX_COUNTER_STEP


def now_epoch() -> int:
    return int(time.time())


@pytest.mark.parametrize("version, held, refused", [
    (2**64 - 1, None, "future"),
    (versions.compose(now_epoch() + 3600, 1), None, "future"),
    (versions.compose(now_epoch() - 100, 50), versions.compose(now_epoch(), 10), "went back"),
    (versions.compose(now_epoch(), 11 + STEP), versions.compose(now_epoch(), 10), "jumps"),
    (versions.compose(now_epoch(), 10 + STEP), versions.compose(now_epoch(), 10), None),
    (versions.compose(now_epoch(), 3), versions.compose(now_epoch() - 50, 900_000), None),  # a restart
    (77, None, None),  # an older coopd: epoch 0
    (0, versions.compose(now_epoch(), 10), None),  # a thesis map: unversioned
], ids=["max", "an-hour-ahead", "epoch-back", "counter-jump", "counter-step", "restart", "epoch-0",
        "unversioned"])  # ids without the clock's values: every pytest-xdist worker collects the same
def test_plausible_versions(version, held, refused):
    why = versions.refusal(version, held)
    assert (why is None) if refused is None else (refused in why), why


def test_a_receiver_whose_clock_is_not_set_checks_order_only():
    """A companion computer without a real-time clock boots in 1970: peers' maps stamped with today's
    epoch are not "from the future" to it, while epochs going back and counter jumps still are."""
    boot_default = 86_400.0  # 1970-01-02
    today = versions.compose(now_epoch(), 5)
    assert not versions.clock_is_set(boot_default) and versions.clock_is_set()
    assert versions.refusal(today, None, now=boot_default) is None
    assert versions.refusal(2**64 - 1, None, now=boot_default) is None  # nothing to bound it by ...
    assert "went back" in versions.refusal(versions.compose(now_epoch() - 10, 9), today, now=boot_default)
    assert "jumps" in versions.refusal(today + STEP + 1, today, now=boot_default)
    assert "future" in versions.refusal(2**64 - 1, None)  # ... once the clock is set, refused again


def send(svc, vid: int, message: bytes, source: str = "127.0.0.1") -> int:
    link = PeerLink.connect(*svc.address, settings(), vid, source=source)
    try:
        return link.send_map(message)[0]
    finally:
        link.close()


def test_a_forged_huge_version_cannot_pin_a_vehicle(server):
    svc = server()
    real = versions.compose(now_epoch(), 5)
    assert send(svc, 9, tm.make(2, 2**63 - 1, b"phantom wall")) == mtp.ACK_VERSION
    assert wait_until(lambda: failures(svc) == {"version": 1}, 3), failures(svc)
    assert svc.received.version(2) == -1
    assert send(svc, 2, tm.make(2, real, b"real map"), source="127.0.0.2") == mtp.ACK_OK
    assert svc.received.version(2) == real


def test_an_epoch_going_back_or_a_counter_jump_is_refused_and_counted(server):
    svc = server()
    held = versions.compose(now_epoch(), 100)
    assert send(svc, 2, tm.make(2, held, b"v")) == mtp.ACK_OK
    assert send(svc, 9, tm.make(2, versions.compose(now_epoch() - 10, 200), b"old boot")) == mtp.ACK_VERSION
    assert send(svc, 9, tm.make(2, held + versions.MAX_COUNTER_STEP + 1, b"jump")) == mtp.ACK_VERSION
    assert wait_until(lambda: failures(svc) == {"version": 2}, 3), failures(svc)
    assert svc.received.version(2) == held


def test_the_real_vehicle_resyncs_after_a_forgery_within_the_bounds():
    """A host stores vehicle 2's map under an epoch 2 s in the future (within the receiver's
    clock-skew bound, here 2 s). Vehicle 2's maps are refused; told so by the acks, it publishes in
    a new epoch (what the daemon does) and its map is stored again within seconds, no one acting."""
    receiver = service(1, max_epoch_ahead_s=2.0)
    refused = []
    sender = None
    try:
        receiver.start()
        forged = versions.compose(now_epoch() + 2, 1)
        assert send(receiver, 9, tm.make(2, forged, b"phantom wall"), source="127.0.0.9") == mtp.ACK_OK
        sender = service(2, "127.0.0.2", peers=["{}:{}".format(*receiver.address)],
                         on_own_refused=lambda *a: refused.append(a))
        sender.start()
        epoch, counter = now_epoch() - 60, 7  # the real vehicle booted a minute ago
        version = versions.compose(epoch, counter)
        sender.publish(tm.make(2, version, b"real"), version)
        t0 = time.monotonic()
        while time.monotonic() - t0 < 10 and tm.payload(receiver.received.get(2).data) != b"real":
            if refused and now_epoch() > epoch:  # the daemon's reaction: a new epoch from the clock
                refused.clear()
                epoch = versions.next_epoch(epoch)
                sender.publish(tm.make(2, versions.compose(epoch, counter), b"real"),
                               versions.compose(epoch, counter))
            time.sleep(0.2)
        assert tm.payload(receiver.received.get(2).data) == b"real", receiver.stats()
        assert time.monotonic() - t0 < 6
        assert failures(receiver).get("version", 0) >= 1
    finally:
        for svc in (sender, receiver):
            if svc is not None:
                svc.stop()


def test_our_own_map_relayed_to_a_peer_first_is_not_taken_for_a_forgery():
    """The receiver already holds vehicle 2's map at the very version vehicle 2 sends (another peer
    relayed it first): it answers 'stale', and vehicle 2 must not take that for a forged newer version
    (which would make it publish everything again in a new epoch): the offer of the next version is
    answered OK."""
    receiver = service(1)
    refused = []
    sender = None
    try:
        receiver.start()
        version = versions.compose(now_epoch() - 60, 7)
        assert send(receiver, 9, tm.make(2, version, b"real"), source="127.0.0.9") == mtp.ACK_OK  # relayed
        sender = service(2, "127.0.0.2", peers=["{}:{}".format(*receiver.address)],
                         on_own_refused=lambda *a: refused.append(a))
        sender.start()
        sender.publish(tm.make(2, version, b"real"), version)
        assert wait_until(lambda: sender.peers.has_version(1, 2) == version, 10)  # it answered 'stale'
        time.sleep(0.5)
        assert refused == [] and tm.payload(receiver.received.get(2).data) == b"real"
    finally:
        for svc in (sender, receiver):
            if svc is not None:
                svc.stop()

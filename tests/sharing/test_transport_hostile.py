"""Hostile peers: random bytes, absurd announcements, slowloris, connection floods, memory pressure.
The server must stay responsive to a well-behaved peer and its buffers must stay bounded."""

import os
import socket
import threading
import time

import pytest
import sharing_testmsg as tm
from sharing_support import failures, free_port, service, settings, wait_until

from coopd.sharing import mtp
from coopd.sharing.transport import DropLog, PeerLink

BS = 256


@pytest.fixture
def server():
    started = []

    def make(**kwargs):
        svc = service(1, **kwargs).start()
        started.append(svc)
        return svc

    yield make
    for svc in started:
        svc.stop()


def good_peer_delivers(svc, vid: int, version: int, within: float = 5.0, source: str = "127.0.0.2",
                       **transport) -> float:
    """A well-behaved peer (on its own address) sends a map, retrying refused connections;
    returns seconds taken."""
    t0 = time.monotonic()
    host, port = svc if isinstance(svc, tuple) else svc.address
    last = None
    while time.monotonic() - t0 < within:
        try:
            link = PeerLink.connect(host, port, settings(**transport), vid, source=source)
            try:
                status, _ = link.send_map(tm.make(vid, version, b"good" * 100))
            finally:
                link.close()
            assert status == mtp.ACK_OK
            return time.monotonic() - t0
        except (OSError, ValueError) as e:
            last = e
            time.sleep(0.1)
    raise AssertionError(f"well-behaved peer could not deliver within {within} s: {last}")


def closed_by_server(s: socket.socket) -> bool:
    """True once the server closed the connection (FIN, or RST because our bytes were unread)."""
    s.settimeout(2)
    try:
        return s.recv(100) == b""
    except ConnectionResetError:
        return True


def test_random_bytes_connections_are_dropped(server):
    svc = server()
    rng = os.urandom
    for i in range(20):
        with socket.create_connection(svc.address, timeout=2) as s:
            junk = rng(300 + i * 37)
            s.sendall((b"\x01" if junk[0] == 0x80 else b"") + junk)
            assert closed_by_server(s)
    assert wait_until(lambda: sum(failures(svc).values()) == 20, 3), failures(svc)
    good_peer_delivers(svc, 5, 1)
    assert svc.received.all()[0].vehicle_id == 5


@pytest.mark.parametrize("blocks", [2**31 - 1, 100_000])
def test_absurd_block_count_is_refused_without_allocating(server, blocks):
    svc = server()
    with socket.create_connection(svc.address, timeout=2) as s:
        s.sendall(mtp.start_frame(blocks, BS))
        assert closed_by_server(s)
    assert wait_until(lambda: failures(svc).get("oversize") == 1, 3)
    assert svc._server.peak_inflight_bytes == 0
    good_peer_delivers(svc, 5, 1)


def test_slowloris_is_cut_by_the_transfer_deadline(server):
    svc = server(transfer_base_s=1.0, min_rate=1e9, read_timeout=0.5)
    s = socket.create_connection(svc.address, timeout=2)
    s.sendall(mtp.start_frame(4, BS))
    t0 = time.monotonic()
    closed_after = None
    try:
        for _ in range(40):  # one byte every 0.1 s: each read is fast, the transfer is not
            s.sendall(b"\x01")
            time.sleep(0.1)
            if failures(svc).get("timeout"):
                closed_after = time.monotonic() - t0
                break
        # meanwhile a well-behaved peer is served
        assert good_peer_delivers(svc, 5, 1) < 3
    finally:
        s.close()
    assert closed_after is not None and closed_after < 2.5, closed_after
    assert svc._server.inflight_bytes == 0 and [m.vehicle_id for m in svc.received.all()] == [5]


def test_silent_connections_time_out_at_the_handshake(server):
    svc = server(handshake_timeout=0.4)
    s = socket.create_connection(svc.address, timeout=2)
    try:
        s.settimeout(2)
        t0 = time.monotonic()
        assert s.recv(10) == b""
        assert time.monotonic() - t0 < 1.5
    finally:
        s.close()
    assert failures(svc).get("timeout") == 1


def test_connection_flood_leaves_room_for_good_peers_and_bounded_threads(server):
    svc = server(max_connections=8, handshake_timeout=0.5)
    base_threads = threading.active_count()
    flood = []
    try:
        for k in range(60):  # a distributed flood: 20 addresses, 3 connections each
            try:
                flood.append(socket.create_connection(svc.address, timeout=1,
                                                      source_address=(f"127.0.1.{10 + k % 20}", 0)))
            except OSError:
                break
        time.sleep(0.1)
        assert svc._server.open_connections <= 8
        assert threading.active_count() <= base_threads + 8
        took = good_peer_delivers(svc, 5, 1, within=8)
    finally:
        for s in flood:
            s.close()
    # a full server makes room by evicting the longest idle (here: silent) connection, else refuses
    assert svc._server.refused_busy + svc._server.evicted_idle > 0 and took < 8
    assert sum(failures(svc).get(cause, 0) for cause in ("busy", "timeout", "evicted")) >= 50


def test_concurrent_transfers_share_a_bounded_byte_budget(server):
    svc = server(max_inflight_bytes=2 * 64 * BS, max_bytes=64 * BS)
    socks = []
    try:
        for _ in range(4):  # each announces 64 blocks and sends nothing more
            s = socket.create_connection(svc.address, timeout=2)
            s.sendall(mtp.start_frame(64, BS))
            socks.append(s)
        assert wait_until(lambda: failures(svc).get("busy") == 2, 3), failures(svc)
        assert svc._server.inflight_bytes == 2 * 64 * BS
        assert svc._server.peak_inflight_bytes <= 2 * 64 * BS
        under_way = svc.stats()["receiving"]  # what coopctl status shows: two transfers, nothing in yet
        assert [(r["vehicle_id"], r["received_bytes"], r["announced_bytes"]) for r in under_way] == \
            [(None, 0, 64 * BS)] * 2
    finally:
        for s in socks:
            s.close()
    assert wait_until(lambda: svc._server.inflight_bytes == 0, 3)
    assert wait_until(lambda: failures(svc).get("cut") == 2, 3), failures(svc)  # counted right after
    good_peer_delivers(svc, 5, 1)


def test_one_address_cannot_take_every_slot(server):
    svc = server(max_connections=8, max_connections_per_address=3, handshake_timeout=2.0)
    flood = [socket.create_connection(svc.address, timeout=1) for _ in range(10)]
    try:
        time.sleep(0.2)
        assert svc._server.open_connections == 3
        assert good_peer_delivers(svc, 5, 1, within=3) < 2  # from another address: served at once
    finally:
        for s in flood:
            s.close()


def test_trickled_frame_after_hello_is_cut(server):
    svc = server(transfer_base_s=1.0, read_timeout=0.5, idle_timeout=30.0)
    link = PeerLink.connect(*svc.address, settings(), 7)  # a proper hello: the connection is idle
    frame = mtp.start_frame(1, BS)
    t0 = time.monotonic()
    try:
        for k in range(40):  # one byte of a control frame every 0.1 s (bounded: 4 s)
            link.sock.sendall(frame[k:k + 1])
            time.sleep(0.1)
            if failures(svc).get("timeout"):
                break
    except OSError:
        pass
    finally:
        link.close()
    assert wait_until(lambda: failures(svc).get("timeout") == 1, 2)
    assert time.monotonic() - t0 < 2.5


def test_server_memory_stays_bounded_under_hostile_announcements(tmp_path):
    """A server process (max_bytes 64 MiB, in-flight budget 128 MiB) is hit by 16 connections
    that each announce a 64 MiB transfer, send 1 MiB and stall: its peak RSS grows by at most
    the budget plus slack, and a well-behaved peer is still served."""
    from netns_support import LoopbackLab, Node

    lab = LoopbackLab()
    lab.add_host(1)
    port = free_port_on(lab.address(1))
    node = Node(lab, 1, 1, port, lab.address(1), "--max-inflight-mb", "128", "--max-connections", "32")
    socks = []
    try:
        base = node.rss_kb()["VmHWM"]
        blocks = (64 << 20) // 4096
        chunk = bytes(1 << 20)
        for _ in range(16):
            s = socket.create_connection((lab.address(1), port), timeout=2)
            try:
                s.sendall(mtp.start_frame(blocks, 4096) + chunk)
            except OSError:
                pass  # refused for lack of budget: the server closed on us
            socks.append(s)
        time.sleep(1.0)
        peak = node.rss_kb()["VmHWM"]
        grown_mb = (peak - base) / 1024
        print(f"server peak RSS grew by {grown_mb:.0f} MiB under 16 x 64 MiB announcements")
        assert grown_mb < 128 + 48, grown_mb
        took = good_peer_delivers((lab.address(1), port), 9, 1, within=8, block_size=4096)
        print(f"well-behaved peer served after {took:.2f} s")
    finally:
        for s in socks:
            s.close()
        node.stop()
        node.log_path.unlink(missing_ok=True)


def free_port_on(host: str) -> int:
    with socket.socket() as s:
        s.bind((host, 0))
        return s.getsockname()[1]


def test_trickle_under_a_large_announcement_is_cut_by_the_rate_floor(server):
    # 1 MiB announced at a 100 kB/s floor would allow ~11 s in total; trickling is cut after ~1 s
    svc = server(transfer_base_s=1.0, min_rate=100_000.0, read_timeout=0.5)
    s = socket.create_connection(svc.address, timeout=2)
    t0 = time.monotonic()
    try:
        s.sendall(mtp.start_frame((1 << 20) // BS, BS))
        for _ in range(40):  # 100 bytes every 0.1 s = 1 kB/s, far below the floor (bounded: 4 s)
            s.sendall(b"\x01" * 100)
            time.sleep(0.1)
            if failures(svc).get("timeout"):
                break
    except OSError:
        pass
    finally:
        s.close()
    assert wait_until(lambda: failures(svc).get("timeout") == 1, 2)
    assert time.monotonic() - t0 < 2.5


def test_drop_warnings_are_limited_per_address_and_the_rest_summed_up(caplog):
    now = [0.0]
    drops = DropLog(burst=3, window_s=60.0, clock=lambda: now[0])
    with caplog.at_level("WARNING", logger="coopd.sharing"):
        logged = [drops.warn("10.0.0.9", None, "frame", "not MTP") for _ in range(50)]
        assert drops.warn("10.0.0.1", 2, "cut", "closed")  # another address has its own burst
        now[0] = 61.0
        assert drops.warn("10.0.0.9", None, "frame", "not MTP")
    assert logged == [True] * 3 + [False] * 47 and drops.held_back == 47
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == 5 and "47 more from 10.0.0.9 not logged" in lines[-1]


def test_drop_log_forgets_addresses_beyond_its_bound():
    now = [0.0]
    drops = DropLog(burst=1, window_s=60.0, clock=lambda: now[0])
    for k in range(3 * DropLog.MAX_ADDRESSES):
        now[0] = k * 1e-3
        drops.warn(f"10.1.{k // 250}.{k % 250}", None, "frame", "x")
    assert len(drops._windows) <= DropLog.MAX_ADDRESSES


def test_a_hostile_host_fills_the_counters_not_the_log(server, caplog):
    svc = server()
    with caplog.at_level("WARNING", logger="coopd.sharing"):
        for _ in range(12):
            with socket.create_connection(svc.address, timeout=2) as s:
                s.sendall(b"\x01" * 300)
                assert closed_by_server(s)
        assert wait_until(lambda: failures(svc).get("frame") == 12, 3), failures(svc)
    dropped = [r for r in caplog.records if "dropped" in r.getMessage()]
    assert len(dropped) == svc._server.drops.burst and svc._server.drops.held_back == 12 - len(dropped)


class Impostor:
    """A host without the swarm key posing as vehicle 2's map server: it answers every hello as a
    keyed vehicle 2 and acks every transfer as stored (bounded: max_conns connections, each read
    with a 0.5 s timeout until it closes)."""

    def __init__(self, host: str, port: int, bs: int, max_conns: int = 20):
        self.bs, self.transfers, self.hellos = bs, 0, 0
        self.listener = socket.create_server((host, port))
        self.listener.settimeout(0.2)
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._serve, args=(max_conns,), daemon=True)
        self.thread.start()

    def _serve(self, max_conns: int) -> None:
        served = 0
        while not self.stop.is_set() and served < max_conns:
            try:
                conn, _ = self.listener.accept()
            except TimeoutError:
                continue
            served += 1
            with conn:
                conn.settimeout(0.5)
                try:
                    self._talk(conn)
                except OSError:
                    pass

    def _frame(self, conn) -> bytes:
        buf = b""
        while len(buf) < self.bs:
            chunk = conn.recv(self.bs - len(buf))
            if not chunk:
                raise ConnectionError("closed")
            buf += chunk
        return buf

    def _talk(self, conn) -> None:
        self._frame(conn)  # the sender's hello
        self.hellos += 1
        conn.sendall(mtp.hello_frame(mtp.Hello(self.bs, 2, os.urandom(16), True, 7)))  # keyed, no tag
        for _ in range(1000):
            _, kind, blocks = mtp.HEAD.unpack_from(self._frame(conn))
            if kind == mtp.OFFER:
                conn.sendall(mtp.ack_frame(0, mtp.ACK_OK, self.bs))
            elif kind == mtp.START:
                for _ in range(blocks + 1):  # the data blocks and the stop frame
                    self._frame(conn)
                self.transfers += 1
                conn.sendall(mtp.ack_frame(blocks, mtp.ACK_OK, self.bs))

    def close(self) -> None:
        self.stop.set()
        self.thread.join(5)
        self.listener.close()


def test_an_impostor_without_the_key_cannot_pose_as_a_vehicle_and_keep_its_maps_away():
    key = b"k" * 32
    port = free_port("127.0.0.31")
    impostor = Impostor("127.0.0.33", port, BS)
    a = service(1, "127.0.0.31", port, peers=["127.0.0.31-127.0.0.33"], peer_ports=[port], swarm_key=key,
                block_size=BS).start()
    b = None
    try:
        a.publish(tm.make(1, 1, b"a" * 1000), 1)
        assert wait_until(lambda: impostor.hellos >= 1, 5)  # a scanned the impostor first
        b = service(2, "127.0.0.32", port, peers=["127.0.0.31"], peer_ports=[port], swarm_key=key,
                    block_size=BS).start()
        assert wait_until(lambda: b.received.version(1) == 1, 5), a.stats()
        assert impostor.transfers == 0
        assert a.peers.snapshot()["unidentified_failures"]["127.0.0.33"].get("auth", 0) >= 1
    finally:
        for svc in (a, b):
            if svc is not None:
                svc.stop()
        impostor.close()

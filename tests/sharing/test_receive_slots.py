"""Slot starvation: connections that only say hello (or nothing) and sit idle cannot keep new
peers out; the longest idle one is evicted for a newcomer, and refusals and evictions are counted."""

import os
import socket

import pytest
from sharing_support import failures, wait_until
from test_transport_hostile import closed_by_server, good_peer_delivers

from coopd.sharing import mtp

BS = 256


def idle_after_hello(svc, source: str) -> socket.socket:
    s = socket.create_connection(svc.address, timeout=2, source_address=(source, 0))
    s.sendall(mtp.hello_frame(mtp.Hello(BS, 250, os.urandom(16), False)))
    s.recv(BS)  # the server's hello: the connection is now idle between transfers
    return s


def is_closed(s: socket.socket) -> bool:
    try:
        return closed_by_server(s)
    except TimeoutError:
        return False


def test_idle_connections_from_many_addresses_cannot_keep_new_peers_out(server):
    svc = server(max_connections=8, max_connections_per_address=4, idle_timeout=30.0, handshake_timeout=30.0)
    flood = [idle_after_hello(svc, f"127.0.3.{10 + k % 4}") for k in range(8)]  # 4 addresses fill it
    try:
        assert svc._server.open_connections == 8
        took = good_peer_delivers(svc, 5, 1, within=5)
        assert took < 3, took  # before: refused 'busy' until idle_timeout (30 s here)
        assert svc.stats()["evicted_idle"] >= 1
        assert closed_by_server(flood[0])  # the longest idle one made room
        assert failures(svc).get("evicted", 0) >= 1
    finally:
        for s in flood:
            s.close()


def test_silent_connections_are_evicted_before_a_peer_that_said_hello(server):
    svc = server(max_connections=4, max_connections_per_address=4, idle_timeout=30.0, handshake_timeout=30.0)
    hello = idle_after_hello(svc, "127.0.3.20")
    silent = [socket.create_connection(svc.address, timeout=2, source_address=("127.0.3.21", 0))
              for _ in range(3)]
    try:
        assert wait_until(lambda: svc._server.open_connections == 4, 2)
        good_peer_delivers(svc, 5, 1, within=5)
        assert svc._server.evicted_idle == 1 and sum(is_closed(s) for s in silent) == 1
        hello.settimeout(0.3)
        with pytest.raises(TimeoutError):
            hello.recv(1)  # still open
    finally:
        hello.close()
        for s in silent:
            s.close()


def test_one_address_at_its_limit_evicts_only_its_own_idle_connection(server):
    svc = server(max_connections=16, max_connections_per_address=2, idle_timeout=30.0)
    mine = [idle_after_hello(svc, "127.0.0.2") for _ in range(2)]
    other = idle_after_hello(svc, "127.0.3.30")
    try:
        good_peer_delivers(svc, 5, 1, within=5, source="127.0.0.2")
        assert closed_by_server(mine[0]) and svc._server.evicted_idle == 1
        other.settimeout(0.3)
        with pytest.raises(TimeoutError):
            other.recv(1)
    finally:
        for s in mine + [other]:
            s.close()

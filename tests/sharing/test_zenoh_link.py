"""Maps over Zenoh (coopd.sharing.zenoh_link): the envelope, and sharing services on loopback that
publish, fetch late, and refuse what the receive path refuses. Sessions listen and connect on
127.0.0.1 only, multicast scouting off."""

import pytest
import sharing_testmsg as tm
from sharing_support import failures, growing_maps, settings, wait_until

from coopd.sharing import delta
from coopd.sharing.service import SharingConfig, SharingService, wire_inspect, wire_verifier
from coopd.sharing.transport import Rejected
from coopd.sharing.zenoh_link import (
    ZenohSettings,
    envelope_cipher,
    key_expr,
    parse_key,
    seal,
    unseal,
)
from tests.ports import zenoh_port

zenoh = pytest.importorskip("zenoh")

KEY = b"k" * 32
OTHER_KEY = b"o" * 32


def test_the_envelope_authenticates_the_message_and_its_key_expression():
    cipher = envelope_cipher(KEY)
    key = key_expr("s", 3, "map")
    message = tm.make(3, 7, b"cells")
    sealed = seal(cipher, key, message)
    assert unseal(cipher, key, sealed) == message and message not in sealed  # encrypted
    with pytest.raises(Rejected, match="authenticate") as e:
        unseal(cipher, key_expr("s", 4, "map"), sealed)  # moved to another vehicle's key expression
    assert e.value.cause == "auth"
    tampered = bytearray(sealed)
    tampered[-1] ^= 1
    for bad, cause in ((bytes(tampered), "auth"), (seal(envelope_cipher(OTHER_KEY), key, message), "auth"),
                       (seal(None, key, message), "auth"), (b"CZ", "malformed"), (b"XX\x00abc", "malformed"),
                       (sealed[:20], "malformed")):
        with pytest.raises(Rejected) as e:
            unseal(cipher, key, bad)
        assert e.value.cause == cause, bad
    assert unseal(None, key, seal(None, key, message)) == message  # open swarm
    with pytest.raises(Rejected, match="has none"):
        unseal(None, key, sealed)


def test_only_this_swarms_keys_are_parsed():
    assert parse_key("s", "coopd/s/3/map") == (3, "map")
    assert parse_key("s", "coopd/s/255/merge") == (255, "result")
    for key in ("coopd/t/3/map", "coopd/s/0/map", "coopd/s/256/map", "coopd/s/x/map", "coopd/s/3/alive",
                "coopd/s/3/map/extra", "other/s/3/map", "coopd/s/0003/map"):
        assert parse_key("s", key) is None, key


def test_liveliness_keys_name_a_valid_vehicle_of_this_swarm():
    alive = {"alive": "alive"}
    assert parse_key("t", "coopd/t/7/alive", alive) == (7, "alive")
    for key in ("coopd/t/7/map", "coopd/other/7/alive", "coopd/t/x/alive", "coopd/t/0/alive",
                "coopd/t/" + "9" * 5000 + "/alive", "coopd/t/7/alive/extra"):
        assert parse_key("t", key, alive) is None, key


def test_settings_are_checked():
    for bad in (dict(swarm="a/b"), dict(swarm=""), dict(mode="linkstate"), dict(listen=("0.0.0.0:7447",)),
                dict(connect=("tcp/",))):
        with pytest.raises(ValueError):
            ZenohSettings(**bad)


def test_shared_memory_is_off_so_maps_cross_tcp_even_on_one_host():
    import json

    from coopd.sharing.zenoh_link import zenoh_config

    conf = zenoh_config(ZenohSettings(listen=("tcp/127.0.0.1:7447",)), 1 << 20)
    assert json.loads(conf.get_json("transport/shared_memory/enabled")) is False


def node(vid: int, listen_port: int, connect=(), key: bytes | None = KEY, swarm: str = "t",
         mode: str = "peer") -> SharingService:
    z = ZenohSettings(swarm=swarm, mode=mode, listen=(f"tcp/127.0.0.1:{listen_port}",),
                      connect=tuple(f"tcp/127.0.0.1:{p}" for p in connect), multicast_scouting=False)
    cfg = SharingConfig(vehicle_id=vid, mtp=False, zenoh=z, transport=settings(swarm_key=key))
    return SharingService(cfg, inspect=tm.inspect).start()


def test_a_map_reaches_a_peer_newer_versions_follow_and_a_late_joiner_fetches_it():
    ports = [zenoh_port() for _ in range(3)]
    a = node(1, ports[0])
    b = node(2, ports[1], connect=[ports[0]])
    late = None
    try:
        assert a.address is None and a.stats()["transports"] == ["zenoh"]
        assert wait_until(lambda: a.stats()["zenoh"]["peers"], 10)
        assert wait_until(lambda: a.awaited_maps() == 1, 10)  # b is alive (its token): its map is awaited
        a.publish(tm.make(1, 5, b"first"), 5)
        assert wait_until(lambda: b.received.version(1) == 5, 10), b.stats()["zenoh"]
        assert tm.payload(b.received.get(1).data) == b"first"
        a.publish(tm.make(1, 6, b"second"), 6)
        assert wait_until(lambda: b.received.version(1) == 6, 10)
        # a vehicle that joins now gets the latest map at once, by query, not by waiting for the next one
        late = node(3, ports[2], connect=[ports[0]])
        assert wait_until(lambda: late.received.version(1) == 6, 10), late.stats()["zenoh"]
        assert late.stats()["zenoh"]["fetched"] >= 1 and a.stats()["zenoh"]["queries_answered"] >= 1
        b.publish(tm.make(2, 9, b"b's"), 9)
        assert wait_until(lambda: a.received.version(2) == 9, 10)
        assert b.received.get(2) is None and failures(b) == {} and failures(a) == {}  # own maps not taken
        assert a.awaited_maps() == 1  # the late vehicle published nothing
        late.stop()
        assert wait_until(lambda: a.awaited_maps() == 0, 10)  # its token went with it
    finally:
        for s in (a, b, late):
            if s is not None:
                s.stop()


def test_what_the_receive_path_refuses_is_counted_and_changes_nothing():
    ports = [zenoh_port() for _ in range(3)]
    receiver = node(2, ports[0])
    wrong_key = node(5, ports[1], connect=[ports[0]], key=OTHER_KEY)
    raw = zenoh.open(_raw_config(ports[2], ports[0]))
    try:
        assert wait_until(lambda: len(receiver.stats()["zenoh"]["peers"]) >= 2, 10)
        wrong_key.publish(tm.make(5, 3, b"x"), 3)  # another swarm key
        cipher = envelope_cipher(KEY)
        # a host with the key is still held to the receive path's rules: a map of vehicle 7 under 6's key
        raw.put(key_expr("t", 6, "map"), seal(cipher, key_expr("t", 6, "map"), tm.make(7, 1, b"x")))
        raw.put(key_expr("t", 8, "map"), b"garbage")  # no envelope
        raw.put(key_expr("t", 9, "map"), seal(cipher, key_expr("t", 9, "map"), b"not a message"))
        def sealed(vid, message):
            return seal(cipher, key_expr("t", vid, "map"), message)

        raw.put(key_expr("t", 10, "map"), sealed(10, tm.make(10, 2, b"x" * 16, size=1)))
        raw.put(key_expr("t", 11, "map"), sealed(11, tm.make(11, 4, b"ok")))
        assert wait_until(lambda: receiver.received.version(11) == 4, 10), receiver.stats()["zenoh"]
        expected = {"auth": 1, "key": 1, "malformed": 2, "size": 1}
        assert wait_until(lambda: failures(receiver) == expected, 10), (failures(receiver), receiver.stats())
        held = {m.vehicle_id for m in receiver.received.all()}
        assert held == {11}
        # an older version of a held map is not taken back
        raw.put(key_expr("t", 11, "map"), seal(cipher, key_expr("t", 11, "map"), tm.make(11, 3, b"old")))
        stale = lambda: receiver.stats()["zenoh"].get("stale", 0) == 1  # noqa: E731
        assert wait_until(stale, 10), receiver.stats()["zenoh"]
        assert receiver.received.version(11) == 4
    finally:
        raw.close()
        wrong_key.stop()
        receiver.stop()


def test_maps_dropped_while_the_receiver_is_busy_are_fetched_again():
    """20 vehicles publish at once into a receiver that takes 50 ms a map: past the 8 waiting, maps
    are dropped as busy, and each dropped vehicle's latest map is then fetched by query, so every
    map arrives (before: the 12 dropped were lost until their next version)."""
    import threading
    import time

    ports = [zenoh_port() for _ in range(2)]
    receiver = node(2, ports[0])
    link = receiver.zenoh
    accept = link._accept
    link._accept = lambda arrival: (time.sleep(0.05), accept(arrival))[1]  # a slow receive path
    raw = zenoh.open(_raw_config(ports[1], ports[0]))
    cipher = envelope_cipher(KEY)
    vids = list(range(20, 40))
    envelopes = {v: seal(cipher, key_expr("t", v, "map"), tm.make(v, 3, bytes([v]) * 64)) for v in vids}
    served = threading.Event()

    def answer(query):  # each vehicle's queryable, as its own session would serve it
        vid = int(str(query.selector.key_expr).split("/")[2])
        if vid in envelopes:
            served.set()
            query.reply(key_expr("t", vid, "map"), envelopes[vid])

    queryables = [raw.declare_queryable(f"coopd/t/{v}/*", answer) for v in vids]
    try:
        assert wait_until(lambda: receiver.stats()["zenoh"]["peers"], 10)
        for v in vids:
            raw.put(key_expr("t", v, "map"), envelopes[v])
        assert wait_until(lambda: all(receiver.received.version(v) == 3 for v in vids), 30), \
            receiver.stats()["zenoh"]
        z = receiver.stats()["zenoh"]
        assert z.get("dropped_busy", 0) >= 1 and served.is_set() and z["fetched"] >= z["dropped_busy"], z
    finally:
        for q in queryables:
            q.undeclare()
        raw.close()
        receiver.stop()


def _raw_config(listen_port: int, connect_port: int):
    import json

    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("listen/endpoints", json.dumps([f"tcp/127.0.0.1:{listen_port}"]))
    conf.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{connect_port}"]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    return conf


def test_routers_carry_a_map_along_a_line():
    """A-B-C-D as routers, each connected to its neighbour only (multicast scouting off; routers do not
    connect to routers they hear of): A's map and D's reach the other end through the routers between."""
    ports = [zenoh_port() for _ in range(4)]
    line = []
    try:
        for i in range(4):
            line.append(node(i + 1, ports[i], connect=[ports[i - 1]] if i else [], mode="router"))
        a, d = line[0], line[3]
        a.publish(tm.make(1, 3, b"from A"), 3)
        d.publish(tm.make(4, 5, b"from D"), 5)
        assert wait_until(lambda: d.received.version(1) == 3 and a.received.version(4) == 5, 15), \
            [s.stats()["zenoh"] for s in line]
        assert [s.received.version(1) for s in line[1:]] == [3, 3, 3]
        assert len(a.stats()["zenoh"]["peers"]) == 0  # A's only session is with router B
    finally:
        for s in line:
            s.stop()


def test_peers_told_of_others_connect_to_them():
    """As peers, connected in a line, they learn of the others by gossip and connect directly: A's
    map reaches D in one hop (where every host is in reach of every other, as on loopback)."""
    ports = [zenoh_port() for _ in range(4)]
    line = []
    try:
        for i in range(4):
            line.append(node(i + 1, ports[i], connect=[ports[i - 1]] if i else []))
        a, d = line[0], line[3]
        assert wait_until(lambda: len(a.stats()["zenoh"]["peers"]) == 3, 15), a.stats()["zenoh"]
        a.publish(tm.make(1, 3, b"from A"), 3)
        assert wait_until(lambda: d.received.version(1) == 3, 15)
    finally:
        for s in line:
            s.stop()


def real_node(vid: int, listen_port: int, connect=()) -> SharingService:
    """A Zenoh-only service reading real map messages (wire format, full decode), deltas on."""
    z = ZenohSettings(swarm="t", listen=(f"tcp/127.0.0.1:{listen_port}",),
                      connect=tuple(f"tcp/127.0.0.1:{p}" for p in connect), multicast_scouting=False)
    s = settings(swarm_key=KEY, max_bytes=4 << 20, max_cells=1 << 22)
    cfg = SharingConfig(vehicle_id=vid, mtp=False, zenoh=z, transport=s)
    return SharingService(cfg, inspect=wire_inspect, verify=wire_verifier(s.max_cells, s.max_bytes)).start()


def test_maps_go_as_deltas_over_zenoh_and_end_bit_identical():
    """Vehicle 1 publishes a growing map version by version: after the first, each goes out as the delta
    from the one before; vehicle 2 ends with vehicle 1's exact message on fewer bytes; a vehicle that
    joins late fetches the full map and then follows the deltas."""
    ports = [zenoh_port() for _ in range(3)]
    maps = growing_maps(12)
    a = real_node(1, ports[0])
    b = real_node(2, ports[1], connect=[ports[0]])
    late = None
    try:
        assert wait_until(lambda: a.stats()["zenoh"]["peers"], 10)
        for grid, v, message in maps[:8]:
            a.publish(message, v, grid)
            assert wait_until(lambda v=v: b.received.version(1) == v, 10), (v, b.stats()["zenoh"])
        late = real_node(3, ports[2], connect=[ports[0]])
        assert wait_until(lambda: late.received.version(1) == 8, 10), late.stats()["zenoh"]
        for grid, v, message in maps[8:]:
            a.publish(message, v, grid)
            assert wait_until(lambda v=v: b.received.version(1) == v and late.received.version(1) == v, 10)
        final = maps[-1][2]
        assert b.received.get(1).data == final and late.received.get(1).data == final  # bit for bit
        za, zb = a.stats()["zenoh"], b.stats()["zenoh"]
        assert zb["accepted_delta"] >= 10 and za["published_delta"] >= 10, (za, zb)
        full_bytes = sum(len(m) for _, _, m in maps)
        print(f"zenoh deltas: {zb['bytes_in']} bytes received for 12 versions, {full_bytes} as full maps")
        assert zb["bytes_in"] < full_bytes / 2
        assert late.stats()["zenoh"]["accepted_delta"] >= 3 and failures(b) == {} and failures(late) == {}
    finally:
        for s in (a, b, late):
            if s is not None:
                s.stop()


def test_a_delta_whose_base_is_not_held_fetches_the_full_map():
    ports = [zenoh_port() for _ in range(2)]
    maps = growing_maps(3)
    receiver = real_node(2, ports[0])
    raw = zenoh.open(_raw_config(ports[1], ports[0]))
    try:
        grid, v, _ = maps[2]
        bricks = delta.BrickLedger()
        for g, ver, m in maps:
            bricks.record(g, ver, m)
        d = bricks.delta_for(2)  # 2 -> 3, and the receiver holds nothing of vehicle 1
        assert d is not None
        key = key_expr("t", 1, "delta")
        assert wait_until(lambda: receiver.stats()["zenoh"]["peers"], 10)
        raw.put(key, seal(envelope_cipher(KEY), key, d))
        assert wait_until(lambda: receiver.stats()["zenoh"].get("delta_refetch") == 1, 10), receiver.stats()
        assert receiver.received.get(1) is None and failures(receiver) == {}  # not a fault of the sender
    finally:
        raw.close()
        receiver.stop()

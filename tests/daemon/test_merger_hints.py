"""The Merger's distributed merging: own warm start, peers' merge results as hints (a wrong one is
refused and the full search decides), counters for the bench, and the results it publishes."""

import time
from types import SimpleNamespace

import numpy as np
import pytest

from coopd.daemon.budget import MemoryBudget
from coopd.daemon.merge_state import MergerSettings, MergeSources
from coopd.daemon.merger import Merger
from coopd.geometry import invert, rigid, rotation_angle_deg, rotation_z
from coopd.merging import merge_all
from coopd.sharing import wire
from coopd.sharing.wire import MapMeta, encode_map
from firmware_sim.benchset import make_chain, make_world


@pytest.fixture(scope="module")
def chain():
    """Maps 0-1 and 1-2 overlap, 0-2 barely: map 2 merges into 0's frame only through map 1."""
    return make_chain(make_world(0), 3, [(6.0, 12.5), (10.0, 12.5), (14.0, 12.5)])


def _truth(maps, i, j):
    return invert(maps[i].world_from_map) @ maps[j].world_from_map


def _close(t, truth, m=0.3, deg=2.0):
    return (np.linalg.norm(np.asarray(t)[:3, 3] - truth[:3, 3]) < m
            and rotation_angle_deg(np.asarray(t)[:3, :3].T @ truth[:3, :3]) < deg)


def _stored(vid, grid, version=1):
    return SimpleNamespace(vehicle_id=vid, version=version, data=encode_map(grid, MapMeta(vid, version)))


def _result_message(vid, *edges):
    return wire.MergeResultMessage(vid, 1, 0.0, tuple(
        wire.MergeEdge(a, b, t, 0.97, 0.3, 1, 1, wire.EDGE_FULL) for a, b, t in edges))


def _merger(chain, peer_results=(), distributed=True, published=None, vehicle_id=0, defer_full_s=0.0,
            published_version=None, peers_alive=None):
    received = [_stored(1, chain[1].grid), _stored(2, chain[2].grid)]
    budget = MemoryBudget(256 << 20, baseline_bytes=0)
    settings = MergerSettings(period_s=3600, distributed=distributed, defer_full_s=defer_full_s)
    sources = MergeSources(lambda: (chain[0].grid.copy(), 4), lambda: received,
                           peer_results=lambda: list(peer_results),
                           publish_results=None if published is None else published.append,
                           published_version=published_version, peers_alive=peers_alive)
    return Merger(vehicle_id, settings, sources, budget, merge_fn=merge_all)


@pytest.mark.slow
@pytest.mark.cpu_bound
def test_own_warm_start_replaces_the_full_search_and_validated_edges_are_published(chain):
    published = []
    m = _merger(chain, published=published, published_version=lambda v: (7 << 32) | v)
    assert m.merge_once("first")["outcome"] == "done"
    s = m.status()
    assert s["full_registrations"] >= 2 and s["hinted"] == 0 and s["cpu_s"] > 0
    assert [o["method"] for o in m.offsets.values()] == ["full", "full"]
    first = published[-1]
    assert first.vehicle_id == 0 and [(e.a, e.b, e.flags) for e in first.edges] == [(0, 1, 1), (0, 2, 1)]
    assert all(_close(e.transform, _truth(chain, 0, e.b)) for e in first.edges)
    # an edge names our map's version as peers hold it (epoch 7, counter 4), and the other map's
    decoded = wire.decode_merge_result(wire.encode_merge_result(first)).edges[0]
    assert (decoded.version_a, decoded.version_b) == ((7 << 32) | 4, 1)
    cpu_first = s["cpu_s"]
    assert m.merge_once("again")["outcome"] == "done"
    s = m.status()
    assert s["full_registrations"] == m.counters["full_registrations"] and s["hinted_own"] == 2
    assert s["hinted"] == 2 and s["hint_rejected"] == 0 and s["full_registrations"] <= 3
    assert [o["method"] for o in m.offsets.values()] == ["hint:own", "hint:own"]
    assert s["cpu_s"] - cpu_first < cpu_first  # the second merge cost less than the first
    # published again only if a transform moved (> 2 cm / 0.2 deg); then the edges are hinted ones
    assert published[-1] is first or {e.flags for e in published[-1].edges} == {0}
    assert all(_close(np.reshape(o["transform"], (4, 4)), _truth(chain, 0, v)) for v, o in m.offsets.items())


@pytest.mark.slow
@pytest.mark.cpu_bound
def test_a_peers_edges_replace_every_full_registration_unless_distributed_is_off(chain):
    peer = [_result_message(1, (1, 0, _truth(chain, 1, 0)), (1, 2, _truth(chain, 1, 2)))]
    m = _merger(chain, peer)
    assert m.merge_once()["outcome"] == "done"
    assert m.counters["full_registrations"] == 0 and m.counters["hinted_peer"] == 2
    assert all(o["accepted"] and o["method"] == "hint:peer" for o in m.offsets.values())
    assert all(_close(np.reshape(o["transform"], (4, 4)), _truth(chain, 0, v)) for v, o in m.offsets.items())
    published = []
    off = _merger(chain, peer, distributed=False, published=published)
    assert off.merge_once()["outcome"] == "done"
    assert off.counters["hinted_peer"] == 0 and off.counters["full_registrations"] >= 2
    assert off.status()["distributed"] is False and published == []  # neither used nor published


@pytest.mark.slow
@pytest.mark.cpu_bound
def test_a_peers_wrong_edge_is_refused_and_the_map_still_merges_correctly(chain):
    wrong = rigid(rotation_z(np.radians(35)), [1.5, -1.0, 0.0]) @ _truth(chain, 1, 0)
    m = _merger(chain, [_result_message(1, (1, 0, wrong))])
    assert m.merge_once()["outcome"] == "done"
    c = m.counters
    assert c["hint_rejected"] >= 1 and c["hinted_peer"] == 0 and c["full_registrations"] >= 2
    assert m.offsets[1]["accepted"] and m.offsets[1]["method"] == "full"
    assert _close(np.reshape(m.offsets[1]["transform"], (4, 4)), _truth(chain, 0, 1))


@pytest.mark.slow
@pytest.mark.cpu_bound
def test_a_higher_vehicle_id_leaves_the_full_search_to_the_lower_one_and_validates_its_result(chain):
    """Vehicle 5 holds maps of 1 and 2: it defers their full search, then merges both from vehicle 1's
    edges (chained through 1 for map 2) without searching at all."""
    peer: list = []
    m = _merger(chain, peer, vehicle_id=5, defer_full_s=3600)
    merge_fn, calls = m.merge_fn, []
    m.merge_fn = lambda *a, **kw: calls.append(1) or merge_fn(*a, **kw)
    assert m.merge_once()["outcome"] == "done"
    assert m.counters["full_registrations"] == 0
    assert all(not o["accepted"] and o["reason"].startswith("deferred") for o in m.offsets.values())
    # every map waits and none has a hint: nothing to fuse, so no merge ran (no map decoded)
    assert calls == [] and "each waits for the result of a lower vehicle id" in m.last["detail"]
    assert m.global_map() is None and m.book.left_out
    requested = m.trigger.requested
    m.on_peer_result()  # a result arrived and maps are left out: merge again, at once (the awaited answer)
    assert m.trigger.requested == requested + 1
    later = time.monotonic() + 3600
    assert m.trigger.wait_due(later, later, m.settings, lambda: None, 0.05)[1] is True
    peer.append(_result_message(1, (1, 5, _truth(chain, 1, 0)), (1, 2, _truth(chain, 1, 2))))
    assert m.merge_once()["outcome"] == "done"
    assert m.counters["full_registrations"] == 0 and m.counters["hinted_peer"] == 2
    # 1's edge to 2 names the versions of maps 1 and 2 we hold: checked, not refined
    assert m.counters["hinted_vouched"] == 1
    assert all(_close(np.reshape(o["transform"], (4, 4)), _truth(chain, 0, v)) for v, o in m.offsets.items())
    requested = m.trigger.requested
    m.on_peer_result()  # nothing left out: no merge for it
    assert m.trigger.requested == requested


@pytest.mark.slow
@pytest.mark.cpu_bound
def test_the_deferral_is_bounded_and_the_lowest_id_never_defers(chain):
    m = _merger(chain, vehicle_id=5, defer_full_s=0.05)
    assert m.merge_once()["outcome"] == "done" and m.counters["full_registrations"] == 0
    time.sleep(0.1)
    assert m.merge_once()["outcome"] == "done" and m.counters["full_registrations"] >= 2
    assert all(o["accepted"] for o in m.offsets.values())
    lowest = _merger(chain, vehicle_id=0, defer_full_s=3600)
    assert lowest.merge_once()["outcome"] == "done" and lowest.counters["full_registrations"] >= 2


def test_unchanged_edges_are_not_published_again(chain):
    published = []
    m = _merger(chain, published=published)
    t = rigid(rotation_z(0.3), [2.0, 1.0, 0.0])

    def edge(transform):
        return wire.MergeEdge(0, 1, transform, 0.97, 0.3, 1, 1, wire.EDGE_FULL)

    m._publish([edge(t)])
    m._publish([edge(rigid(rotation_z(0.3 + np.radians(0.1)), [2.01, 1.0, 0.0]))])  # within 2 cm / 0.2 deg
    assert len(published) == 1
    m._publish([edge(rigid(rotation_z(0.3), [2.1, 1.0, 0.0]))])
    m._publish([edge(t), wire.MergeEdge(0, 2, t, 0.97, 0.3, 1, 1, 0)])
    assert len(published) == 3 and published[-1].version > published[0].version


def _daemon_config(tmp_path, **merging):
    from daemon_harness import in_process_memory_mb, swarm_key_file

    from coopd.daemon.config import from_dict

    return from_dict({
        "vehicle": {"mavlink": "udpin:127.0.0.1:21160"},
        "camera": {"source": f"socket:{tmp_path}/no-camera.sock"},
        "sharing": {"enabled": True, "listen_host": "127.0.0.1", "port": 21161,
                    "swarm_key_file": str(swarm_key_file(tmp_path))},
        "merging": merging,
        "daemon": {"state_dir": str(tmp_path / "state"), "control_socket": str(tmp_path / "control.sock"),
                   "memory_mb": in_process_memory_mb()},
    })


def test_the_daemon_hands_its_merge_results_to_sharing_and_peers_results_to_the_merger(tmp_path):
    from coopd.daemon.service import Daemon

    d = Daemon(_daemon_config(tmp_path), merge_fn=merge_all)
    assert d.merger.settings.distributed is True
    msg = _result_message(1, (1, 3, rigid(rotation_z(0.2), [1.0, 0.0, 0.0])))
    d.merger.sources.publish_results(msg)
    pending = d.sharing.pending_for(7)
    assert [(origin, version, kind) for origin, version, _, kind in pending] == [(1, 1, "result")]
    assert wire.decode_merge_result(pending[0][2]).edges[0].b == 3
    assert d.sharing.results.offer(_result_message(5, (5, 1, np.eye(4))))
    assert [r.vehicle_id for r in d.merger.sources.peer_results()] == [5]
    status = d.merger.status()
    assert {"full_registrations", "hinted", "hinted_own", "hinted_peer", "hint_rejected", "cpu_s",
            "done", "failed", "deferred", "offsets", "last"} <= set(status)
    central = Daemon(_daemon_config(tmp_path, distributed=False), merge_fn=merge_all)
    assert central.merger.settings.distributed is False


def test_command_line_switches_distributed_merging_off():
    from coopd.daemon.main import build_config, parse_args

    assert build_config(parse_args(["--no-config"])).merging.distributed is True
    assert build_config(parse_args(["--no-config", "--no-distributed"])).merging.distributed is False


@pytest.mark.slow
@pytest.mark.cpu_bound
def test_a_lower_id_alive_whose_map_has_not_come_takes_the_search(chain):
    """Vehicle 3 holds only maps of higher ids (4 and 5) while vehicle 2 is alive, its map not come
    yet: vehicle 2 searches them, so vehicle 3 waits for its result instead of searching itself.
    With no lower id alive, vehicle 3 is the lowest and searches."""
    received = [_stored(4, chain[1].grid), _stored(5, chain[2].grid)]
    settings = MergerSettings(period_s=3600, distributed=True, defer_full_s=3600)

    def merger(alive: frozenset[int]) -> Merger:
        sources = MergeSources(lambda: (chain[0].grid.copy(), 4), lambda: received,
                               peer_results=lambda: [], peers_alive=lambda: alive)
        return Merger(3, settings, sources, MemoryBudget(256 << 20, baseline_bytes=0), merge_fn=merge_all)

    m = merger(frozenset({2, 4}))
    assert m.merge_once()["outcome"] == "done"
    assert m.counters["full_registrations"] == 0
    assert all(not o["accepted"] and o["reason"].startswith("deferred") for o in m.offsets.values())
    m = merger(frozenset({4, 6}))
    assert m.merge_once()["outcome"] == "done"
    assert m.counters["full_registrations"] == 2

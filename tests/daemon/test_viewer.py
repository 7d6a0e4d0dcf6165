"""The viewer: bricks and runs (pure), then a real Foxglove WebSocket client on loopback that
subscribes to the map and pose channels and decodes what the server sends."""

import base64
import secrets
import shutil
import sys
import threading

import numpy as np
import pytest

from coopd.daemon.config import ViewerConfig
from coopd.daemon.viewer import (
    BRICK_EDGE,
    OWN,
    PEER,
    SOURCE_COLOURS,
    BrickTracker,
    MapViewer,
    brick_cubes,
    brick_id,
    brick_views,
    labels_of,
    runs_along_x,
)
from coopd.grid import OccupancyGrid
from coopd.vehicle.pose_buffer import PoseSample

pytest.importorskip("foxglove")
pytest.importorskip("websockets")
pytest.importorskip("google.protobuf")
from tests.daemon.foxglove_client import FoxgloveClient  # noqa: E402

RES = 0.1


def small_map() -> OccupancyGrid:
    """40 x 40 x 20 cells, offset (-20, -20, -10): a wall along x, a post, free cells elsewhere."""
    grid = OccupancyGrid.empty((40, 40, 20), RES)
    grid.cells[:, :, :10] = 0
    grid.cells[3:30, 5, 2] = 100  # a run of 27 cells crossing two bricks along x
    grid.cells[33, 33, 0:15] = 90  # a post
    return grid


def occupied_keys(grid: OccupancyGrid) -> set[tuple[int, int, int]]:
    return {tuple(k) for k in (np.argwhere(grid.cells >= 50) + grid.offset).tolist()}


def keys_of_cubes(cubes) -> set[tuple[int, int, int]]:
    """The cell keys a list of (centre, size) cubes covers (runs along x)."""
    keys = set()
    for (cx, cy, cz), (sx, _, _) in cubes:
        n = int(round(sx / RES))
        x0 = int(round(cx / RES - (n - 1) / 2))
        keys |= {(x0 + i, int(round(cy / RES)), int(round(cz / RES))) for i in range(n)}
    return keys


def test_runs_along_x_cover_exactly_the_labelled_cells():
    rng = np.random.default_rng(1)
    block = rng.choice([0, OWN, PEER], size=(16, 16, 16), p=[0.7, 0.2, 0.1]).astype(np.int8)
    rebuilt = np.zeros_like(block)
    for x0, y, z, length, label in runs_along_x(block):
        assert np.all(block[x0:x0 + length, y, z] == label)
        rebuilt[x0:x0 + length, y, z] = label
    assert np.array_equal(rebuilt, block)


def test_bricks_are_aligned_on_absolute_keys_and_only_changed_ones_come_back():
    grid = small_map()
    labels = labels_of(grid.cells, None)
    keys, blocks = brick_views(labels, grid.offset, 16)
    # offset -20 -> bricks -2..1 along x; the wall (x keys -17..9, y -15, z -8) and the post
    assert {tuple(k) for k in keys.tolist()} == {(-2, -1, -1), (-1, -1, -1), (0, -1, -1),
                                                  (0, 0, -1), (0, 0, 0)}
    cubes = [c[:2] for k, b in zip(keys.tolist(), blocks, strict=True) for c in brick_cubes(k, b, RES, 16)]
    assert keys_of_cubes(cubes) == occupied_keys(grid)
    tracker = BrickTracker(16)
    changed, emptied = tracker.changes([brick_views(labels, grid.offset, 16)])
    assert len(changed) == 5 and emptied == []
    # the same map in two slabs split on a brick boundary (key -16) is the same bricks: nothing changed
    halves = [brick_views(labels[:4], grid.offset, 16), brick_views(labels[4:], grid.offset + (4, 0, 0), 16)]
    assert tracker.changes(halves) == ({}, [])
    grid.cells[33, 33, 0:15] = 0  # the post goes: its two bricks are emptied
    grid.cells[35, 2, 3] = 100  # one new cell in a new brick
    changed, emptied = tracker.changes([brick_views(labels_of(grid.cells, None), grid.offset, 16)])
    assert set(changed) == {(0, -2, -1)} and sorted(emptied) == [(0, 0, -1), (0, 0, 0)]


def test_source_labels_own_cells_and_peer_only_cells():
    merged = small_map()
    local = np.full(merged.shape, -1, dtype=np.int8)
    local[3:30, 5, 2] = 100
    labels = labels_of(merged.cells, local, by_source=True)
    assert np.all(labels[3:30, 5, 2] == OWN) and np.all(labels[33, 33, 0:15] == PEER)
    assert np.count_nonzero(labels) == len(occupied_keys(merged))


class FakeDaemon:
    """The viewer's inputs: a local map under a lock, an installable global map, a pose, peers."""

    def __init__(self):
        self.local = small_map()
        self.lock = threading.Lock()
        self.merged = None
        self.sample = PoseSample(5.0, np.array([1.0, 2.0, 0.5]), np.array([1.0, 0.0, 0.0, 0.0]))
        self.peer_transforms = {}

    def viewer(self) -> MapViewer:
        return MapViewer(ViewerConfig(enabled=True, port=0), local_map=lambda: (self.local, self.lock),
                         global_map=lambda: self.merged, pose=lambda: self.sample,
                         peers=lambda: self.peer_transforms, status=lambda: {"state": "mapping"})


def receive(client: FoxgloveClient, topics: set[str]) -> dict:
    """The next message of each topic."""
    got = {}
    while not topics <= set(got):
        topic, _, message = client.next_message()
        got[topic] = message
    return got


def wait_subscribed(viewer: MapViewer, topics) -> None:
    assert viewer.subscribed(topics, 10.0), f"the server never saw the subscriptions to {topics}"


def cubes_of(entity) -> list:
    return [((c.pose.position.x, c.pose.position.y, c.pose.position.z), (c.size.x, c.size.y, c.size.z))
            for c in entity.cubes]


def test_a_foxglove_client_receives_the_map_pose_peers_and_status():
    daemon = FakeDaemon()
    viewer = daemon.viewer()
    viewer.start()
    try:
        client = FoxgloveClient(f"ws://127.0.0.1:{viewer.port}")
        try:
            topics = {"/map", "/tf", "/track", "/status"}
            client.subscribe(sorted(topics))
            assert client.server_info["name"] == "coopd"
            assert client.channels["/map"]["schemaName"] == "foxglove.SceneUpdate"
            wait_subscribed(viewer, topics)
            viewer.tick()
            got = receive(client, topics)
            # before a merge the view is the local map: every occupied cell centre, nothing else
            scene = got["/map"]
            assert {e.frame_id for e in scene.entities} == {"map"}
            sent = [c for e in scene.entities for c in cubes_of(e)]
            assert keys_of_cubes(sent) == occupied_keys(daemon.local)
            bricks = {brick_id(np.floor_divide(k, BRICK_EDGE)) for k in occupied_keys(daemon.local)}
            assert {e.id for e in scene.entities} == bricks and len(scene.deletions) == 0
            (tf,) = got["/tf"].transforms
            assert (tf.parent_frame_id, tf.child_frame_id) == ("map", "base_link")
            assert (tf.translation.x, tf.translation.y, tf.translation.z) == (1.0, 2.0, 0.5)
            assert len(got["/track"].poses) == 1 and got["/status"] == {"state": "mapping"}

            # a merge installs a global map differing in one brick, and a peer's frame is accepted
            merged = small_map()
            merged.cells[20, 5, 2] = 0  # key (0, -15, -8)
            brick = tuple(np.floor_divide((0, -15, -8), BRICK_EDGE))
            daemon.merged = (merged, None)
            turn = np.eye(4)
            turn[:3, :3] = [[0, -1, 0], [1, 0, 0], [0, 0, 1]]
            turn[:3, 3] = [4.0, -1.0, 0.0]
            daemon.peer_transforms = {7: turn}
            viewer.tick()
            got = receive(client, {"/map", "/tf"})
            (entity,) = got["/map"].entities
            assert entity.id == brick_id(brick) and len(got["/map"].deletions) == 0
            in_brick = {k for k in occupied_keys(merged) if tuple(np.floor_divide(k, BRICK_EDGE)) == brick}
            assert keys_of_cubes(cubes_of(entity)) == in_brick and len(in_brick) > 0
            peer = got["/tf"].transforms[1]
            assert (peer.parent_frame_id, peer.child_frame_id) == ("map", "vehicle_7")
            assert (peer.translation.x, peer.translation.y) == (4.0, -1.0)
            assert (peer.rotation.z, peer.rotation.w) == pytest.approx((np.sqrt(0.5), np.sqrt(0.5)))

            # that brick emptied: deleted by id; nothing else is sent
            emptied = merged.copy()
            emptied.cells[3, 5, 2] = 0  # key (-17, -15, -8): the wall's only cell in its brick (edge 8 or 16)
            daemon.merged = (emptied, None)
            viewer.tick()
            scene = receive(client, {"/map"})["/map"]
            gone = brick_id(np.floor_divide((-17, -15, -8), BRICK_EDGE))
            assert [d.id for d in scene.deletions] == [gone] and len(scene.entities) == 0
            assert viewer.status()["bricks"] == len(bricks) - 1
        finally:
            client.close()
    finally:
        viewer.close()


def test_the_daemon_serves_and_records_the_viewer_only_when_enabled_and_stops_it(monkeypatch):
    from daemon_harness import in_process_memory_mb, workdir

    from coopd.cli.daemon_commands import format_status
    from coopd.daemon.config import from_dict
    from coopd.daemon.service import Daemon, StartupError
    from tests.loopback_fc import free_port

    wd = workdir("coopd-viewer-")
    port = free_port()

    def config(**viewer):
        return from_dict({
            "vehicle": {"id": 1, "mavlink": f"udpin:127.0.0.1:{free_port()}"},
            "camera": {"source": f"socket:{wd}/camera.sock"},
            "sharing": {"enabled": False},
            "viewer": viewer,
            "daemon": {"state_dir": str(wd / "state"), "control_socket": str(wd / "control.sock"),
                       "memory_mb": in_process_memory_mb()},
        })

    d = Daemon(config(enabled=True, port=port, rate_hz=5.0, record_dir=str(wd / "rec")), merge_fn=None)
    d.start()
    try:
        client = FoxgloveClient(f"ws://127.0.0.1:{port}")
        try:
            client.subscribe(["/status", "/tf"])
            got = receive(client, {"/status", "/tf"})
            assert got["/status"]["viewer"]["enabled"] and got["/status"]["viewer"]["url"] == f"ws://127.0.0.1:{port}"
            assert list(got["/tf"].transforms) == []  # no odometry yet: no base_link, no peers
            assert any(t["role"] == "viewer" for t in d.priorities.report())
            row = [line for line in format_status(d.handle_status({})).splitlines() if "viewer" in line]
            assert row and f"ws://127.0.0.1:{port} at 5.0 Hz" in row[0]
            rows = format_status(d.handle_status({})).splitlines()
            assert any("recording" in line and str(wd / "rec") in line for line in rows)
        finally:
            client.close()
    finally:
        d.request_stop("test")
        d.shutdown()
    with pytest.raises(OSError):
        FoxgloveClient(f"ws://127.0.0.1:{port}", timeout_s=2.0)
    (recording,) = (wd / "rec").glob("coopd-vehicle1-*.mcap")  # closed complete at shutdown
    # nothing was mapped (no camera): no /map message
    assert {topic for topic, _ in recorded(recording)} == {"/status", "/tf", "/track"}

    d = Daemon(config(enabled=True, port=port), merge_fn=None)
    monkeypatch.setitem(sys.modules, "foxglove", None)  # the drone install: no SDK
    try:
        with pytest.raises(StartupError, match="foxglove SDK is missing"):
            d._start_viewer()
    finally:
        monkeypatch.undo()
        d.shutdown()

    d = Daemon(config(), merge_fn=None)
    try:
        assert d.viewer is None and d.handle_status({})["viewer"] == {"enabled": False}
    finally:
        d.shutdown()
        shutil.rmtree(wd, ignore_errors=True)


def test_only_loopback_addresses_count_as_loopback():
    from coopd.daemon.viewer import is_loopback, url_of

    assert is_loopback("127.0.0.1") and is_loopback("127.3.0.1") and is_loopback("::1")
    assert not is_loopback("0.0.0.0") and not is_loopback("10.0.0.5") and not is_loopback("::")
    assert url_of("::1", 8765) == "ws://[::1]:8765" and url_of("127.0.0.1", 1) == "ws://127.0.0.1:1"


def recorded(path) -> list[tuple[str, object]]:
    """(topic, decoded message) of every message in an MCAP file, decoded as the client decodes."""
    from mcap.reader import make_reader

    client = FoxgloveClient.__new__(FoxgloveClient)  # its decoding, without a connection
    client._classes = {}
    out = []
    with open(path, "rb") as f:
        for schema, channel, message in make_reader(f).iter_messages():
            described = {"id": channel.id, "encoding": channel.message_encoding,
                         "schemaName": schema.name if schema else "",
                         "schema": base64.b64encode(schema.data).decode() if schema else ""}
            out.append((channel.topic, client.decode(described, message.data)))
    return out


def test_colour_by_source_tells_own_cells_from_cells_only_peers_mapped(tmp_path):
    daemon = FakeDaemon()
    daemon.local.cells[33, 33, 0:15] = 0  # our map has the wall; the post is only in the global map
    daemon.merged = (small_map(), None)
    config = ViewerConfig(enabled=False, colour="source", record_dir=str(tmp_path))
    viewer = MapViewer(config, local_map=lambda: (daemon.local, daemon.lock),
                       global_map=lambda: daemon.merged, pose=lambda: None, peers=lambda: {},
                       status=lambda: {})
    viewer.start()
    try:
        viewer.tick()
    finally:
        viewer.close()
    (scene,) = [m for topic, m in recorded(viewer.recording) if topic == "/map"]
    colours = {}
    for entity in scene.entities:
        for cube in entity.cubes:
            colour = (round(cube.color.r, 2), round(cube.color.g, 2), round(cube.color.b, 2))
            colours.setdefault(colour, []).append(((cube.pose.position.x, cube.pose.position.y,
                                                    cube.pose.position.z), (cube.size.x, 0, 0)))
    assert set(colours) == {SOURCE_COLOURS[OWN], SOURCE_COLOURS[PEER]}
    assert {k[:2] for k in keys_of_cubes(colours[SOURCE_COLOURS[PEER]])} == {(13, 13)}  # the post
    assert {(k[1], k[2]) for k in keys_of_cubes(colours[SOURCE_COLOURS[OWN]])} == {(-15, -8)}  # the wall


def test_a_recording_holds_the_map_pose_and_status_and_stops_at_its_size_limit(tmp_path):
    daemon = FakeDaemon()
    config = ViewerConfig(enabled=False, record_dir=str(tmp_path / "rec"), record_max_mb=1)
    viewer = MapViewer(config, local_map=lambda: (daemon.local, daemon.lock),
                       global_map=lambda: daemon.merged, pose=lambda: daemon.sample, peers=lambda: {},
                       status=lambda: {"state": "mapping"}, vehicle_id=3)
    viewer.start()
    try:
        assert viewer.port is None  # recording only: nothing listens
        viewer.tick()
        daemon.local.cells[0, 0, 0] = 100
        viewer.tick()
    finally:
        viewer.close()
    path = tmp_path / "rec" / viewer.recording.rsplit("/", 1)[1]
    assert path.name.startswith("coopd-vehicle3-") and path.suffix == ".mcap"
    topics = []
    for topic, decoded in recorded(path):
        topics.append(topic)
        if topic == "/map" and topics.count("/map") == 1:
            sent = [c for e in decoded.entities for c in cubes_of(e)]
            assert keys_of_cubes(sent) == occupied_keys(small_map())
        elif topic == "/map":  # the second tick: only the brick of the new cell
            new_brick = brick_id(np.floor_divide((-20, -20, -10), BRICK_EDGE))
            assert [e.id for e in decoded.entities] == [new_brick]
    assert topics.count("/map") == 2 and topics.count("/tf") == 2 and topics.count("/status") == 2
    assert viewer.status()["recording"]["open"] is False and viewer.status()["recording"]["bytes"] > 0

    big = MapViewer(config, local_map=lambda: (daemon.local, daemon.lock), global_map=lambda: None,
                    pose=lambda: None, peers=lambda: {}, status=lambda: {"pad": secrets.token_hex(200_000)})
    big.start()
    try:
        for _ in range(16):  # 16 x 400 kB of hex (about 200 kB compressed each) against 1 MiB
            big.tick()
        assert big.status()["recording"]["stopped"] == "record_max_mb 1 reached"
        assert big.recording != viewer.recording  # a new file per start
    finally:
        big.close()


def test_with_nobody_watching_the_map_is_not_read():
    daemon = FakeDaemon()
    reads = []
    viewer = MapViewer(ViewerConfig(enabled=True, port=0),
                       local_map=lambda: reads.append(1) or (daemon.local, daemon.lock),
                       global_map=lambda: reads.append(1) or daemon.merged, pose=lambda: daemon.sample,
                       peers=lambda: {}, status=lambda: reads.append(1) or {})
    viewer.start()
    try:
        viewer.tick()
        assert reads == [] and viewer.status()["bricks"] == 0 and viewer.counters["ticks"] == 1
        assert len(viewer.track) == 1  # the track is kept all the same
    finally:
        viewer.close()


@pytest.mark.parametrize("host, warned",
                         [("0.0.0.0", True), ("10.1.2.3", True), ("127.0.0.1", False), ("::1", False)])
def test_a_viewer_off_loopback_is_logged_as_unauthenticated(monkeypatch, caplog, host, warned):
    """Off loopback only with open = true (the config refuses it otherwise), and a warning at start."""
    import foxglove

    class NotListening:  # stands in for the SDK's server: the test binds nothing outside loopback
        port = 8765

        def stop(self):
            pass

    asked = []
    monkeypatch.setattr(foxglove, "start_server", lambda **kw: asked.append(kw) or NotListening())
    daemon = FakeDaemon()
    viewer = MapViewer(ViewerConfig(enabled=True, host=host, open=warned),
                       local_map=lambda: (daemon.local, daemon.lock), global_map=lambda: None,
                       pose=lambda: None, peers=lambda: {}, status=lambda: {})
    with caplog.at_level("WARNING", logger="coopd.daemon"):
        viewer.start()
    viewer.close()
    assert asked[0]["host"] == host and asked[0]["port"] == 8765
    warnings = [r for r in caplog.records if r.levelname == "WARNING" and "no authentication" in r.message]
    assert bool(warnings) == warned


def test_a_large_update_is_split_into_messages_of_bounded_bricks(monkeypatch, tmp_path):
    import coopd.daemon.viewer as viewer_module

    monkeypatch.setattr(viewer_module, "BRICKS_PER_MESSAGE", 2)
    daemon = FakeDaemon()
    viewer = MapViewer(ViewerConfig(record_dir=str(tmp_path)), local_map=lambda: (daemon.local, daemon.lock),
                       global_map=lambda: None, pose=lambda: None, peers=lambda: {}, status=lambda: {})
    viewer.start()
    try:
        viewer.tick()
    finally:
        viewer.close()
    scenes = [m for topic, m in recorded(viewer.recording) if topic == "/map"]
    bricks = {brick_id(np.floor_divide(k, BRICK_EDGE)) for k in occupied_keys(daemon.local)}
    assert len(scenes) == -(-len(bricks) // 2) and all(len(s.entities) <= 2 for s in scenes)
    sent = [c for s in scenes for e in s.entities for c in cubes_of(e)]
    assert {e.id for s in scenes for e in s.entities} == bricks
    assert keys_of_cubes(sent) == occupied_keys(daemon.local)


def test_after_a_failed_update_every_brick_is_sent_again(tmp_path):
    daemon = FakeDaemon()
    failing = []

    def global_map():
        if failing:
            raise OSError("the map could not be read")
        return daemon.merged

    viewer = MapViewer(ViewerConfig(record_dir=str(tmp_path)), local_map=lambda: (daemon.local, daemon.lock),
                       global_map=global_map, pose=lambda: None, peers=lambda: {}, status=lambda: {})
    viewer.start()
    try:
        viewer.tick()
        failing.append(1)
        with pytest.raises(OSError):
            viewer.tick()
        failing.clear()
        viewer.tick()
    finally:
        viewer.close()
    first, again = [m for topic, m in recorded(viewer.recording) if topic == "/map"]
    assert {e.id for e in again.entities} == {e.id for e in first.entities} != set()

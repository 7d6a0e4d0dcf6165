"""Checkpoints: round trip, corrupt files set aside, disk full, kill -9 mid-write."""

import errno
import multiprocessing
import os
import random
import signal
import subprocess
import time

import numpy as np
import pytest

from coopd.daemon.checkpoint import CheckpointStore, VersionReserve
from coopd.grid import OccupancyGrid
from coopd.sharing.wire import DecodeLimits, MapMeta, encode_map, encode_thesis_map


def make_grid(seed: int, shape=(30, 20, 10)) -> OccupancyGrid:
    rng = np.random.default_rng(seed)
    cells = rng.choice(np.array([-1, -1, -1, 0, 20, 90], np.int8), size=shape).astype(np.int8)
    return OccupancyGrid(cells, 0.1, (-15, -10, -2))


@pytest.fixture
def store(tmp_path):
    return CheckpointStore(tmp_path / "state", keep=3)


def test_round_trip_and_pruning(store):
    grids = [make_grid(i) for i in range(5)]
    paths = [store.save("local", g, MapMeta(4, version=i, stamp=10.0 + i)) for i, g in enumerate(grids)]
    assert all(p is not None for p in paths)
    assert [p.name for p in paths][-1] == "local.0000000005.cmap"
    assert [seq for seq, _ in store.generations("local")] == [5, 4, 3]
    cp = store.load_latest("local")
    assert cp.seq == 5 and cp.meta == MapMeta(4, 4, 14.0) and cp.grid.same_cells(grids[4])
    assert cp.grid.offset.tolist() == [-15, -10, -2] and cp.grid.resolution == pytest.approx(0.1)
    assert store.stats()["saved"] == 5 and store.stats()["set_aside"] == 0


def test_received_maps_are_kept_as_messages(store):
    msg = encode_map(make_grid(9), MapMeta(7, 3, 5.0))
    assert store.save_message("peer-7", msg).read_bytes() == msg
    assert store.save("local", make_grid(1), MapMeta(1))
    loaded = store.load_all()
    assert set(loaded) == {"local", "peer-7"} and loaded["peer-7"].meta.vehicle_id == 7
    assert store.save_message("peer-8", encode_thesis_map(make_grid(1), 8)) is None  # no CRC: refused
    assert store.save_message("peer-8", b"garbage") is None
    assert store.failed == 2 and store.generations("peer-8") == []


def test_missing_means_none(store):
    assert store.load_latest("local") is None
    with pytest.raises(ValueError):
        store.load_latest("../etc")


def _damage_truncate(path):
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])


def _damage_flip_payload(path):
    data = bytearray(path.read_bytes())
    data[-5] ^= 0x40
    path.write_bytes(bytes(data))


def _damage_flip_header(path):
    data = bytearray(path.read_bytes())
    data[12] ^= 0x01  # inside the shape fields
    path.write_bytes(bytes(data))


def _damage_empty(path):
    path.write_bytes(b"")


def _damage_text(path):
    path.write_text("this is not a map\n")


def _damage_thesis(path):
    path.write_bytes(encode_thesis_map(make_grid(3), 4))  # a valid message, but no CRC: not ours


def _damage_appended(path):
    with open(path, "ab") as f:
        f.write(b"\x00" * 10)


DAMAGE = [
    _damage_truncate,
    _damage_flip_payload,
    _damage_flip_header,
    _damage_empty,
    _damage_text,
    _damage_thesis,
    _damage_appended,
]


@pytest.mark.parametrize("damage", DAMAGE, ids=[d.__name__[8:] for d in DAMAGE])
def test_corrupt_newest_is_set_aside_and_previous_loaded(store, damage):
    good = make_grid(1)
    store.save("local", good, MapMeta(2, 1))
    newest = store.save("local", make_grid(2), MapMeta(2, 2))
    damage(newest)
    cp = store.load_latest("local")
    assert cp.meta.version == 1 and cp.grid.same_cells(good)
    assert not newest.exists()
    aside = [p.name for p in newest.parent.iterdir() if ".corrupt-" in p.name]
    assert len(aside) == 1 and aside[0].startswith(newest.name + ".corrupt-")
    assert store.set_aside == 1 and "set aside" in store.problems[-1]
    # saving goes on normally after a set-aside
    assert store.save("local", make_grid(3), MapMeta(2, 3)) is not None
    assert store.load_latest("local").meta.version == 3


def test_all_corrupt_loads_nothing(store):
    for i in range(3):
        _damage_flip_payload(store.save("local", make_grid(i), MapMeta(1, i)))
    assert store.load_latest("local") is None
    assert store.set_aside == 3


def test_oversized_checkpoint_is_refused(tmp_path):
    store = CheckpointStore(tmp_path, limits=DecodeLimits(max_cells=1000, max_bytes=1 << 20))
    store.save("local", make_grid(1), MapMeta(1))  # 6000 cells
    assert store.load_latest("local") is None and store.set_aside == 1


def test_disk_full_keeps_previous_checkpoint_monkeypatched(store, monkeypatch):
    store.save("local", make_grid(1), MapMeta(1, 1))

    def full(fd):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(os, "fsync", full)
    assert store.save("local", make_grid(2), MapMeta(1, 2)) is None
    monkeypatch.undo()
    assert store.failed == 1 and "ENOSPC" in store.last_error
    assert sorted(p.name for p in store.directory.iterdir()) == ["local.0000000001.cmap"]  # no temp left
    assert store.load_latest("local").meta.version == 1


@pytest.fixture
def tiny_tmpfs(tmp_path):
    mnt = tmp_path / "tiny"
    mnt.mkdir()
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=256k", "tmpfs", str(mnt)], capture_output=True)
    if r.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {r.stderr.decode().strip()}")
    try:
        yield mnt
    finally:
        subprocess.run(["umount", str(mnt)], check=False)


def test_disk_full_on_a_real_tiny_tmpfs(tiny_tmpfs):
    store = CheckpointStore(tiny_tmpfs, keep=3)
    small = OccupancyGrid(np.full((20, 20, 10), -1, np.int8), 0.1)
    assert store.save("local", small, MapMeta(1, 1)) is not None
    size = store.last_path.stat().st_size
    filler = tiny_tmpfs / "filler"
    with open(filler, "wb", buffering=0) as f:  # fill the disk to the last byte
        try:
            while True:
                f.write(b"\xff" * 4096)
                f.flush()
        except OSError as e:
            assert e.errno == errno.ENOSPC
    big = make_grid(5, shape=(60, 60, 20))  # random cells: compresses badly, ~tens of KiB
    assert store.save("local", big, MapMeta(1, 2)) is None
    assert "ENOSPC" in store.last_error
    assert store.load_latest("local").meta.version == 1
    assert store.last_path.stat().st_size == size
    assert [p.name for p in tiny_tmpfs.iterdir() if p.name.endswith(".tmp")] == []
    filler.unlink()
    assert store.save("local", big, MapMeta(1, 3)) is not None  # space back: saving resumes
    assert store.load_latest("local").grid.same_cells(big)


def test_version_reserve_is_written_ahead_and_read_back(tmp_path, monkeypatch):
    reserve = VersionReserve(tmp_path, step=100)
    assert reserve.reserved == 0 and reserve.ensure(5) and reserve.reserved == 105
    written = (tmp_path / "version-reserve.json").stat().st_mtime_ns
    assert reserve.ensure(105) and (tmp_path / "version-reserve.json").stat().st_mtime_ns == written
    assert VersionReserve(tmp_path).reserved == 105  # what a restarted daemon sees

    def full(fd):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(os, "fsync", full)
    assert not reserve.ensure(106) and reserve.failed == 1 and reserve.reserved == 105
    monkeypatch.undo()
    for junk in (b"\x00not json", b'{"reserved": -4}', b'{"reserved": true}', b"{}"):
        (tmp_path / "version-reserve.json").write_bytes(junk)
        assert VersionReserve(tmp_path).reserved == 0


def test_unfinished_temp_files_are_cleaned_on_open(tmp_path):
    (tmp_path / ".local.0000000003.cmap.x1y2z3.tmp").write_bytes(b"half")
    (tmp_path / "unrelated.tmp").write_bytes(b"keep")
    store = CheckpointStore(tmp_path)
    assert store.temp_removed == 1 and (tmp_path / "unrelated.tmp").exists()


def _checkpoint_forever(directory: str, seed: int) -> None:
    store = CheckpointStore(directory, keep=2)
    version = store.load_latest("local").meta.version if store.generations("local") else 0
    rng = np.random.default_rng(seed)
    while True:
        version += 1
        n = int(rng.integers(10, 40))
        cells = rng.choice(np.array([-1, 0, 30, 90], np.int8), size=(n, n, 8)).astype(np.int8)
        store.save("local", OccupancyGrid(cells, 0.1), MapMeta(1, version, float(version)))


def _newest_seq(directory: str) -> int:
    """Read-only look at the directory (opening a store would clean the writer's temp files)."""
    seqs = [
        int(n.split(".")[1]) for n in os.listdir(directory) if n.startswith("local.") and n.endswith(".cmap")
    ]
    return max(seqs, default=0)


def test_kill_9_during_repeated_checkpoints_never_loads_corrupt(tmp_path):
    """20 times: a child writes checkpoints in a loop and is SIGKILLed at a random moment;
    the next start always loads a valid checkpoint and never finds a corrupt one."""
    ctx = multiprocessing.get_context("fork")
    directory = str(tmp_path / "state")
    CheckpointStore(directory)
    rnd = random.Random(1)
    last_version = 0
    mid_write = 0
    for i in range(20):
        before = _newest_seq(directory)
        child = ctx.Process(target=_checkpoint_forever, args=(directory, i))
        child.start()
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline:  # let it write at least one checkpoint, then kill at random
            if _newest_seq(directory) > before:
                break
            time.sleep(0.002)
        time.sleep(rnd.uniform(0.0, 0.05))
        os.kill(child.pid, signal.SIGKILL)
        child.join()
        store = CheckpointStore(directory, keep=2)
        mid_write += store.temp_removed
        cp = store.load_latest("local")
        assert cp is not None, f"round {i}: nothing loadable"
        assert store.set_aside == 0, store.problems
        assert cp.meta.version > last_version
        last_version = cp.meta.version
    print(f"20 kills, {mid_write} of them inside write_atomic (temp file left), last version {last_version}")


def test_checkpoints_are_private_whatever_the_umask(store):
    """Maps of the swarm stay readable by the daemon's user only, also under a lax umask."""
    old = os.umask(0)
    try:
        path = store.save("local", make_grid(1), MapMeta(1))
        peer = store.save_message("peer-7", encode_map(make_grid(2), MapMeta(7)))
    finally:
        os.umask(old)
    assert [p.stat().st_mode & 0o777 for p in (path, peer)] == [0o600, 0o600]

"""Checkpoints: maps saved atomically to the StateDirectory and resumed from on start.

Each map has a name ("local", "global", "peer-5", ...) and numbered generations on disk:

    /var/lib/coopd/local.0000000042.cmap     one coopd map message (wire format, CRC-32)

A save writes the next generation with write_atomic (temp file, fsync, rename, fsync dir) and
then prunes all but the newest `keep`; a failed save (ENOSPC, EIO, ...) is counted and logged,
never fatal, and leaves the earlier generations untouched. load_latest() tries the newest
generation first; one that is torn, corrupt, of the wrong type or oversized is renamed to
`*.corrupt-<UTC time>` (kept for inspection, never loaded again) and the next older one is tried.
"""

import errno
import json
import logging
import os
import re
import threading
import time
from dataclasses import dataclass
from pathlib import Path

from coopd.grid import OccupancyGrid
from coopd.io import atomic
from coopd.io.cmap import read_cmap_bytes
from coopd.sharing import versions
from coopd.sharing.wire import (
    DEFAULT_LIMITS,
    MSG_COOPD_MAP,
    DecodeLimits,
    MapMeta,
    WireError,
    decode_map,
    encode_map,
    peek,
)

log = logging.getLogger("coopd.daemon")

NAME = re.compile(r"[a-z0-9][a-z0-9_-]{0,63}")
FILE = re.compile(r"(?P<name>[a-z0-9][a-z0-9_-]{0,63})\.(?P<seq>\d{10})\.cmap")
TEMP = re.compile(r"\.[a-z0-9][a-z0-9_-]{0,63}\.\d{10}\.cmap\..+\.tmp")
"""What write_atomic leaves behind when the process dies mid-write."""


@dataclass(frozen=True)
class Checkpoint:
    """A loaded checkpoint."""

    name: str
    seq: int
    path: Path
    grid: OccupancyGrid
    meta: MapMeta
    size: int


class CheckpointStore:
    """Numbered, atomically written map checkpoints of one directory; see the module docstring."""

    def __init__(
        self, directory, keep: int = 3, limits: DecodeLimits = DEFAULT_LIMITS, encoding: str = "default"
    ):
        if keep < 1:
            raise ValueError("keep must be >= 1")
        self.directory = Path(directory)
        self.keep = keep
        self.limits = limits
        self.encoding = encoding
        self.saved = 0
        self.failed = 0
        self.set_aside = 0
        self.temp_removed = 0
        self.last_path: Path | None = None
        self.last_save_time: float | None = None
        self.last_error: str | None = None
        self.problems: list[str] = []
        """One line per checkpoint set aside or save that failed, for the operator (bounded)."""
        self._lock = threading.Lock()
        self.directory.mkdir(mode=0o750, parents=True, exist_ok=True)
        self._remove_temp_files()

    # ------------------------------------------------------------------------------------ listing
    def generations(self, name: str) -> list[tuple[int, Path]]:
        """(seq, path) of the checkpoints of `name`, newest first."""
        _check_name(name)
        out = []
        for entry in os.scandir(self.directory):
            m = FILE.fullmatch(entry.name)
            if m and m.group("name") == name and entry.is_file(follow_symlinks=False):
                out.append((int(m.group("seq")), Path(entry.path)))
        return sorted(out, reverse=True)

    def names(self) -> list[str]:
        """Names with at least one checkpoint file."""
        found = {m.group("name") for e in os.scandir(self.directory) if (m := FILE.fullmatch(e.name))}
        return sorted(found)

    # ------------------------------------------------------------------------------------- saving
    def save(self, name: str, grid: OccupancyGrid, meta: MapMeta) -> Path | None:
        """Write grid + meta as the next checkpoint of `name`; the path, or None if it failed."""
        try:
            data = encode_map(grid, meta, self.encoding)
        except (ValueError, MemoryError) as e:
            return self._failed(name, f"cannot encode: {e}")
        return self.save_message(name, data)

    def save_message(self, name: str, data: bytes) -> Path | None:
        """Write an already encoded coopd map message (e.g. a received map, still compressed)."""
        _check_name(name)
        try:
            info = peek(data)
        except WireError as e:
            return self._failed(name, f"not a map message: {e}")
        if info.message_type != MSG_COOPD_MAP or info.crc32 is None or info.total_size != len(data):
            return self._failed(name, "only complete coopd map messages (type 1, with CRC) are checkpointed")
        with self._lock:
            gens = self.generations(name)
            seq = (gens[0][0] + 1) if gens else 1
            path = self.directory / f"{name}.{seq:010d}.cmap"
            t0 = time.monotonic()
            try:
                atomic.write_atomic(path, data, atomic.PRIVATE)
            except OSError as e:
                code = errno.errorcode.get(e.errno, str(e.errno))
                return self._failed(name, f"{code}: {e.strerror or e}")
            self.saved += 1
            self.last_path = path
            self.last_save_time = time.time()
            self.last_error = None
            removed = self._prune(name, [(seq, path)] + gens)
        log.info(
            "checkpoint %s: %d bytes in %.0f ms (map version %d, %d old removed)",
            path.name,
            len(data),
            1000 * (time.monotonic() - t0),
            info.map_version,
            removed,
        )
        return path

    def _failed(self, name: str, why: str) -> None:
        self.failed += 1
        self.last_error = f"{name}: {why}"
        self._problem(f"checkpoint of {name} failed ({why}); earlier checkpoints kept")
        log.error("checkpoint of %s failed (%s); earlier checkpoints kept", name, why)
        return None

    def _prune(self, name: str, gens: list[tuple[int, Path]]) -> int:
        return _unlink([path for _, path in sorted(gens, reverse=True)[self.keep :]])

    # ------------------------------------------------------------------------------------ loading
    def load_latest(self, name: str = "local", max_cells: int | None = None) -> Checkpoint | None:
        """The newest valid checkpoint of `name` (invalid newer ones are set aside), or None.
        `max_cells`: a map with more cells is set aside unread (e.g. a received map too large to
        merge within the memory budget must not come back after a restart and block merges)."""
        with self._lock:
            for seq, path in self.generations(name):
                try:
                    data = read_cmap_bytes(path, self.limits)
                    info = peek(data)
                    if info.message_type != MSG_COOPD_MAP or info.crc32 is None:
                        raise WireError(f"message type {info.message_type} without CRC is not a checkpoint")
                    if max_cells is not None and info.cells > max_cells:
                        raise WireError(f"{info.cells} cells, more than the {max_cells} this daemon can "
                                        f"merge within its memory budget")
                    grid, meta = decode_map(data, self.limits)
                except (WireError, ValueError, MemoryError) as e:
                    self._set_aside(path, str(e))
                    continue
                except OSError as e:  # unreadable (EIO, EACCES): leave it, try the older ones
                    self._problem(f"checkpoint {path.name} unreadable: {e}")
                    log.error("checkpoint %s unreadable: %s", path, e)
                    continue
                log.info(
                    "resuming %s from %s: %s cells, map version %d",
                    name,
                    path.name,
                    "x".join(map(str, grid.shape)),
                    meta.version,
                )
                return Checkpoint(name, seq, path, grid, meta, len(data))
        return None

    def remove(self, name: str) -> int:
        """Delete every generation of `name` (a map no longer held); returns how many."""
        with self._lock:
            return _unlink([path for _, path in self.generations(name)])

    def load_all(self) -> dict[str, Checkpoint]:
        """The newest valid checkpoint of every name on disk."""
        out = {}
        for name in self.names():
            cp = self.load_latest(name)
            if cp is not None:
                out[name] = cp
        return out

    def _set_aside(self, path: Path, why: str) -> None:
        stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime())
        target = path.with_name(f"{path.name}.corrupt-{stamp}")
        n = 1
        while target.exists():
            n += 1
            target = path.with_name(f"{path.name}.corrupt-{stamp}-{n}")
        try:
            os.rename(path, target)
        except OSError as e:
            log.error("corrupt checkpoint %s (%s) cannot be set aside: %s", path, why, e)
            self._problem(f"corrupt checkpoint {path.name} ({why}) could not be set aside: {e}")
            return
        self.set_aside += 1
        self._problem(f"corrupt checkpoint {path.name} ({why}) set aside as {target.name}")
        log.error("corrupt checkpoint %s (%s): set aside as %s, not loaded", path.name, why, target.name)

    def _problem(self, line: str) -> None:
        self.problems.append(line)
        del self.problems[:-20]

    def _remove_temp_files(self) -> None:
        for entry in os.scandir(self.directory):
            if TEMP.fullmatch(entry.name):
                try:
                    os.unlink(entry.path)
                    self.temp_removed += 1
                except OSError:
                    pass
        if self.temp_removed:
            log.info("removed %d unfinished checkpoint temp files in %s", self.temp_removed, self.directory)

    def stats(self) -> dict:
        """Plain data for `coopctl status`."""
        return {
            "directory": str(self.directory),
            "saved": self.saved,
            "failed": self.failed,
            "set_aside": self.set_aside,
            "last_path": str(self.last_path) if self.last_path else None,
            "last_save_time": self.last_save_time,
            "last_error": self.last_error,
            "problems": list(self.problems),
        }


def _check_name(name: str) -> None:
    if not isinstance(name, str) or not NAME.fullmatch(name):
        raise ValueError(f"checkpoint name {name!r} must match {NAME.pattern}")


VERSION_FILE = "version-reserve.json"
VERSION_STEP = 10_000
"""Versions reserved per write: a daemon killed -9 resumes at most this far above its last map."""


class VersionReserve:
    """Local map versions are reserved on disk before they are published, so a daemon killed -9
    (whose checkpoint may be older than what it already shared) resumes above every version a
    peer may hold: one (vehicle, version) never names two different maps. `reserved` is the
    highest version counter that may have been published. The file also keeps the version epoch
    (coopd.sharing.versions): every start, and every new epoch, is above the last one written."""

    def __init__(self, directory: Path, step: int = VERSION_STEP):
        self.path = Path(directory) / VERSION_FILE
        self.step = step
        self.failed = 0
        self.reserved = self._read("reserved", 2**31)
        self.epoch = self._read("epoch", 2**32)
        """The last version epoch written (0: none yet); new_epoch() moves it on."""

    def _read(self, key: str, bound: int) -> int:
        try:
            with open(self.path, "rb") as f:
                doc = json.loads(f.read(256))
            value = doc.get(key, 0) if key == "epoch" else doc[key]
        except FileNotFoundError:
            return 0
        except (OSError, ValueError, KeyError, TypeError, AttributeError) as e:
            log.error("%s unreadable (%s): map versions resume from the checkpoint", self.path, e)
            return 0
        if not isinstance(value, int) or isinstance(value, bool) or not 0 <= value < bound:
            log.error("%s holds no valid %s: map versions resume from the checkpoint", self.path, key)
            return 0
        return value

    def new_epoch(self) -> int:
        """A version epoch above every one this daemon used before (written first; if the write
        fails it is still used, counted and logged: it is above the last one written)."""
        epoch = versions.next_epoch(self.epoch)
        self._write(self.reserved, epoch)
        self.epoch = epoch
        return epoch

    def _write(self, reserved: int, epoch: int) -> bool:
        try:
            atomic.write_atomic(self.path, json.dumps({"reserved": reserved, "epoch": epoch}).encode(),
                               atomic.PRIVATE)
        except OSError as e:
            self.failed += 1
            if self.failed == 1 or self.failed % 100 == 0:
                log.error("cannot reserve map versions in %s (%s, %d times)", self.path, e, self.failed)
            return False
        return True

    def ensure(self, version: int) -> bool:
        """Make sure `version` is within the reserve (one write per `step` versions); False if the
        reserve could not be written (e.g. disk full: counted and logged, publishing goes on)."""
        if version <= self.reserved:
            return True
        reserved = min(version + self.step, 2**31 - 1)
        if not self._write(reserved, self.epoch):
            return False
        self.reserved = reserved
        return True


def _unlink(paths: list[Path]) -> int:
    """Delete checkpoint files; how many went (one already gone is no error, others are logged)."""
    removed = 0
    for path in paths:
        try:
            path.unlink()
            removed += 1
        except FileNotFoundError:
            pass
        except OSError as e:
            log.warning("cannot remove checkpoint %s: %s", path, e)
    return removed

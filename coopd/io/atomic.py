"""Crash-safe file replacement: temp file in the same directory, fsync, rename, fsync dir."""

import os
import tempfile
from pathlib import Path

PRIVATE = 0o600
"""The mode of files only their owner may read: the daemon's checkpoints and state."""


def current_umask() -> int:
    """The process' umask, read without changing it (os.umask would race with other threads)."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    mask = os.umask(0o077)  # no /proc: the classic read-and-restore
    os.umask(mask)
    return mask


def write_atomic(path, data, mode: int | None = None) -> None:
    """Replace `path` with `data` so that readers see the old file or the new one, never a mix.

    The file gets `mode`, or with None what a plain open() would give: 0666 less the umask (the
    temporary file is 0600 until written, so nobody reads it half-written). Secrets and the
    daemon's state pass PRIVATE.
    """
    path = Path(path)
    directory = path.parent if str(path.parent) else Path(".")
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=directory)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fchmod(f.fileno(), 0o666 & ~current_umask() if mode is None else mode)
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise
    dir_fd = os.open(directory, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
    try:
        os.fsync(dir_fd)
    finally:
        os.close(dir_fd)

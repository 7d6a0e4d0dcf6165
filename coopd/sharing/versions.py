"""Map versions that cannot be pinned (docs/protocol.md, "Map versions").

A coopd map version is a uint64: the sender's epoch in the high 32 bits (Unix seconds when its
current version sequence began: its start, or the moment it found its versions refused) and a
counter in the low 32 bits. Versions below 2**32 (epoch 0) come from older coopds and tools.

A receiver accepts a version only if it is plausible: its epoch is not in the future (beyond a
clock-skew allowance), not older than the epoch it holds for that vehicle, and within one epoch
the counter does not jump further than a vehicle could map in days. A forged 2**64 - 1 is
refused, and a forgery within the bounds holds only until the real vehicle starts a new epoch.

A receiver whose own clock is not set (a companion computer without a real-time clock reads a date
before CLOCK_SET_AFTER until NTP or GPS sets it) cannot tell the future: it checks the order of
epochs and counters only, rather than refusing every peer's map as "from the future".
"""

import time

EPOCH_SHIFT = 32
COUNTER_MASK = (1 << EPOCH_SHIFT) - 1
MAX_EPOCH_AHEAD_S = 300.0
"""Clock skew tolerated between vehicles: an epoch further in the future is refused."""
MAX_COUNTER_STEP = 1 << 24
"""Largest counter step within one epoch (16.7 M map versions: days of mapping at 30 frames/s)."""
CLOCK_SET_AFTER = 1_767_225_600
"""2026-01-01T00:00:00Z: a system clock reading earlier than this has not been set."""


def clock_is_set(now: float | None = None) -> bool:
    """Whether the system clock reads a plausible date (not a board's power-on default)."""
    return (time.time() if now is None else now) >= CLOCK_SET_AFTER


def compose(epoch: int, counter: int) -> int:
    """The version of `counter` in `epoch`."""
    if not (0 <= epoch <= COUNTER_MASK and 0 <= counter <= COUNTER_MASK):
        raise ValueError(f"epoch {epoch} / counter {counter} outside 0..2**32-1")
    return (epoch << EPOCH_SHIFT) | counter


def split(version: int) -> tuple[int, int]:
    """(epoch, counter) of a version."""
    return version >> EPOCH_SHIFT, version & COUNTER_MASK


def next_epoch(previous: int, now: float | None = None) -> int:
    """A new epoch: the clock's seconds, and always above the previous one."""
    return max(int(time.time() if now is None else now), previous + 1)


def refusal(version: int, held: int | None, now: float | None = None,
            max_ahead_s: float = MAX_EPOCH_AHEAD_S, max_step: int = MAX_COUNTER_STEP) -> str | None:
    """Why `version` is implausible next to the `held` version of the same vehicle (None: no map
    held), or None if it is plausible. Version 0 (a thesis map, unversioned) is always plausible;
    whether a plausible version is newer than the held one is the caller's comparison."""
    if version == 0:
        return None
    epoch, counter = split(version)
    now = time.time() if now is None else now
    if clock_is_set(now) and epoch > now + max_ahead_s:
        return f"version {version} has epoch {epoch}, {epoch - now:.0f} s in the future"
    if not held:
        return None
    held_epoch, held_counter = split(held)
    if epoch < held_epoch:
        return f"version {version}: epoch {epoch} went back (holding epoch {held_epoch})"
    if epoch == held_epoch and counter - held_counter > max_step:
        return (f"version {version}: counter jumps by {counter - held_counter} within epoch {epoch} "
                f"(at most {max_step})")
    return None

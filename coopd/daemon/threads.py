"""Thread priorities (a nice value per role, applied to the calling native thread) and the
progress of the worker threads that the watchdog's health check watches.

Linux schedules threads individually, so setpriority(PRIO_PROCESS, tid) changes one thread
(threads it starts afterwards inherit the value). Lowering nice below the current value needs
CAP_SYS_NICE (the unit grants it); without it a high-priority role runs at nice 0 and the
report says so. Requested and applied values are reported by `coopctl status`.
"""

import logging
import os
import threading
import time
from contextlib import contextmanager
from dataclasses import dataclass

log = logging.getLogger("coopd.daemon")

ROLE_NICE = {
    "mavlink": -5,
    "camera": -3,
    "mapping": -3,
    "obstacles": -3,
    "sharing": 0,
    "control": 0,
    "merging": 10,
    "viewer": 15,
}
"""Nice per role (design: mavlink highest; camera, mapping, obstacles high; sharing, control normal;
merging low; the operator's live view lowest)."""


def run_at_rate(step, rate_hz: float, stop: threading.Event, counters: dict, name: str,
                beat=lambda: None) -> None:
    """Call step() every 1/rate_hz s until stop is set (late steps do not pile up); an exception in one
    step is counted in counters["errors"], logged for the first three, and the next step comes as usual.
    beat() is called before each step (WorkerProgress.beat: a step that hangs stops the beats)."""
    period = 1.0 / rate_hz
    next_at = time.monotonic()
    while not stop.is_set():
        beat()
        try:
            step()
        except Exception:
            counters["errors"] += 1
            if counters["errors"] <= 3:
                log.exception("%s: update failed (%d so far)", name, counters["errors"])
        next_at = max(next_at + period, time.monotonic())
        stop.wait(max(0.0, next_at - time.monotonic()))


@dataclass(frozen=True)
class ThreadPriority:
    role: str
    thread: str
    tid: int
    requested: int
    applied: int
    note: str = ""


def read_nice(tid: int) -> int:
    """The nice value of one live thread of this process, read back from the kernel (getpriority on
    its tid: one system call, where reading /proc/self/task/<tid>/stat costs about 60 times more, and
    status reads it for every thread, each time it is asked)."""
    return os.getpriority(os.PRIO_PROCESS, tid)


class ThreadPriorities:
    """Applies role priorities to threads and remembers what was asked and what was got."""

    def __init__(self, role_nice: dict[str, int] | None = None):
        self.role_nice = dict(ROLE_NICE if role_nice is None else role_nice)
        self._applied: dict[int, tuple[ThreadPriority, threading.Thread]] = {}
        self._lock = threading.Lock()

    def apply(self, role: str) -> ThreadPriority:
        """Set the calling thread's nice for `role`; never raises for missing privileges."""
        if role not in self.role_nice:
            raise ValueError(f"unknown thread role {role!r}; known: {', '.join(self.role_nice)}")
        requested = self.role_nice[role]
        tid = threading.get_native_id()
        note = ""
        try:
            os.setpriority(os.PRIO_PROCESS, tid, requested)
        except PermissionError:
            fallback = max(requested, 0)
            try:
                os.setpriority(os.PRIO_PROCESS, tid, fallback)
                note = f"nice {requested} needs CAP_SYS_NICE; running at {fallback}"
            except PermissionError:
                note = f"nice {requested} not permitted; left unchanged"
        except OSError as e:
            note = f"setpriority failed: {e}"
        applied = os.getpriority(os.PRIO_PROCESS, tid)
        result = ThreadPriority(role, threading.current_thread().name, tid, requested, applied, note)
        with self._lock:
            self._applied[tid] = (result, threading.current_thread())
        if note:
            log.warning("thread %s (%s, tid %d): %s", result.thread, role, tid, note)
        else:
            log.info("thread %s (%s, tid %d): nice %d", result.thread, role, tid, applied)
        return result

    def report(self) -> list[dict]:
        """Live threads with their role, requested and current nice (read back from the kernel)."""
        out = []
        with self._lock:
            items = list(self._applied.items())
        for tid, (prio, thread) in items:
            try:
                if not thread.is_alive():
                    raise ProcessLookupError(tid)
                current = read_nice(tid)
            except (OSError, ValueError, IndexError):  # the thread has ended
                with self._lock:
                    if self._applied.get(tid, (None, None))[1] is thread:
                        del self._applied[tid]
                continue
            out.append(dict(vars(prio), applied=current))
        return sorted(out, key=lambda d: (d["requested"], d["role"]))


MIN_CPU_PROGRESS_S = 0.001
"""CPU seconds a working thread must have used since the last mark to count as progressing (a
thread blocked on a lock still uses a few microseconds on its way into the wait)."""


class WorkerProgress:
    """Whether each watched worker thread makes progress, for the systemd watchdog.

    A worker calls beat(name) every time round its loop. A worker inside one long step (a merge,
    encoding a big map) runs it under working(name): it then counts as progressing while its
    thread's CPU time grows, so a long computation is not mistaken for a hang but a thread
    blocked on a lock, a socket or a sleep is. A worker that neither looped within max_age_s nor,
    while working, used CPU within busy_quiet_s is stalled.
    """

    def __init__(self, names, max_age_s: float = 3.0, busy_quiet_s: float = 30.0):
        now = time.monotonic()
        self.max_age_s, self.busy_quiet_s = max_age_s, busy_quiet_s
        self._beats = dict.fromkeys(names, now)
        self._cpu_clock: dict[str, int] = {}
        self._busy: dict[str, list[float]] = {}  # name -> [step started, CPU seconds seen, when it grew]
        self._lock = threading.Lock()

    def watched(self) -> list[str]:
        return list(self._beats)

    def beat(self, name: str) -> None:
        """Called by the worker itself each time round its loop (names not watched are ignored)."""
        if name not in self._beats:
            return
        if name not in self._cpu_clock:
            try:
                self._cpu_clock[name] = time.pthread_getcpuclockid(threading.get_ident())
            except (AttributeError, OSError):  # no per-thread CPU clocks here: beats only
                self._cpu_clock[name] = -1
        self._beats[name] = time.monotonic()

    @contextmanager
    def working(self, name: str):
        """Wrap one long step of the worker (called by the worker itself)."""
        self.beat(name)
        now = time.monotonic()
        with self._lock:
            self._busy[name] = [now, self._cpu(name), now]
        try:
            yield
        finally:
            with self._lock:
                self._busy.pop(name, None)
            self.beat(name)

    def _cpu(self, name: str) -> float:
        clock = self._cpu_clock.get(name, -1)
        if clock == -1:
            return -1.0
        try:
            return time.clock_gettime(clock)
        except OSError:  # the thread has ended
            return -1.0

    def stalled(self) -> dict[str, str]:
        """Workers not making progress, with the reason for the operator."""
        now = time.monotonic()
        out = {}
        with self._lock:
            for name, beat in self._beats.items():
                age = now - beat
                if age <= self.max_age_s:
                    continue
                busy = self._busy.get(name)
                if busy is None:
                    out[name] = f"has not looped for {age:.1f} s"
                    continue
                cpu = self._cpu(name)
                if cpu - busy[1] >= MIN_CPU_PROGRESS_S:
                    busy[1], busy[2] = cpu, now
                quiet = now - busy[2]
                if quiet > self.busy_quiet_s:
                    out[name] = f"in one step for {now - busy[0]:.1f} s without using CPU for {quiet:.1f} s"
        return out

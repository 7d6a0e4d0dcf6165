"""Thread priorities: a nice value per role, applied to the calling native thread.

Linux schedules threads individually, so setpriority(PRIO_PROCESS, tid) changes one thread
(threads it starts afterwards inherit the value). Lowering nice below the current value needs
CAP_SYS_NICE (the unit grants it); without it a high-priority role runs at nice 0 and the
report says so. Requested and applied values are reported by `coopctl status`.
"""

import logging
import os
import threading
from dataclasses import asdict, dataclass

log = logging.getLogger("coopd.daemon")

ROLE_NICE = {
    "mavlink": -5,
    "camera": -3,
    "mapping": -3,
    "sharing": 0,
    "control": 0,
    "merging": 10,
}
"""Nice per role (design: mavlink highest; camera, mapping high; sharing, control normal; merging low)."""


@dataclass(frozen=True)
class ThreadPriority:
    role: str
    thread: str
    tid: int
    requested: int
    applied: int
    note: str = ""


def read_nice(tid: int) -> int:
    """The nice value of one thread of this process, from /proc/self/task/<tid>/stat (field 19)."""
    with open(f"/proc/self/task/{tid}/stat", "rb") as f:
        stat = f.read().decode()
    fields = stat[stat.rindex(")") + 2 :].split()  # after "pid (comm) ": field 3 onwards
    return int(fields[19 - 3])


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
            out.append(dict(asdict(prio), applied=current))
        return sorted(out, key=lambda d: (d["requested"], d["role"]))

"""Thread priorities: per-thread nice applied, visible in /proc/self/task/<tid>/stat, reported; the
watchdog's view of worker progress."""

import os
import sys
import threading
import time
from collections import Counter

import pytest

from coopd.daemon.threads import ROLE_NICE, ThreadPriorities, WorkerProgress, run_at_rate


def nice_in_proc(tid: int) -> int:
    """A thread's nice as /proc/self/task/<tid>/stat shows it (field 19): the kernel's view, checked
    independently of the getpriority call the daemon uses."""
    with open(f"/proc/self/task/{tid}/stat", "rb") as f:
        stat = f.read().decode()
    return int(stat[stat.rindex(")") + 2 :].split()[19 - 3])


def run_in_thread(fn):
    out, hold = {}, threading.Event()

    def body():
        out["value"] = fn()
        out["tid"] = threading.get_native_id()
        out["nice_proc"] = nice_in_proc(out["tid"])
        hold.wait(5)

    t = threading.Thread(target=body, name="test-role")
    t.start()
    while "nice_proc" not in out and t.is_alive():
        t.join(0.01)
    return out, hold, t


def test_low_priority_role_is_visible_in_proc():
    prios = ThreadPriorities()
    out, hold, t = run_in_thread(lambda: prios.apply("merging"))
    try:
        assert out["value"].requested == 10 and out["value"].applied == 10 and out["value"].note == ""
        assert out["nice_proc"] == 10
        assert nice_in_proc(threading.get_native_id()) != 10  # only that thread changed
        report = prios.report()
        assert [(r["role"], r["tid"], r["applied"]) for r in report] == [("merging", out["tid"], 10)]
    finally:
        hold.set()
        t.join()
    assert prios.report() == []  # ended threads drop out of the report


@pytest.mark.skipif(os.geteuid() != 0, reason="raising priority needs root / CAP_SYS_NICE")
def test_high_priority_role_with_privilege():
    prios = ThreadPriorities()
    out, hold, t = run_in_thread(lambda: prios.apply("mavlink"))
    try:
        assert out["value"].applied == ROLE_NICE["mavlink"] == -5 and out["nice_proc"] == -5
    finally:
        hold.set()
        t.join()


def test_high_priority_without_privilege_is_reported_not_fatal():
    """As an unprivileged user (RLIMIT_NICE 0, no CAP_SYS_NICE), mavlink asks -5 and gets 0."""
    r, w = os.pipe()
    pid = os.fork()
    if pid == 0:
        code = 1
        try:
            os.close(r)
            if os.geteuid() == 0:
                import resource

                resource.setrlimit(resource.RLIMIT_NICE, (0, 0))
                os.setgroups([])
                os.setgid(65534)
                os.setuid(65534)
            prios = ThreadPriorities()
            out, hold, t = run_in_thread(lambda: prios.apply("mavlink"))
            hold.set()
            t.join()
            p = out["value"]
            os.write(w, f"{p.requested} {p.applied} {out['nice_proc']} {p.note}".encode())
            code = 0
        except BaseException as e:  # report, never return into pytest from the child
            os.write(w, f"error {e!r}".encode())
        finally:
            sys.stdout.flush()
            os._exit(code)
    os.close(w)
    with os.fdopen(r) as f:
        text = f.read()
    os.waitpid(pid, 0)
    requested, applied, proc, note = text.split(" ", 3)
    assert (requested, applied, proc) == ("-5", "0", "0"), text
    assert "CAP_SYS_NICE" in note


def test_unknown_role():
    with pytest.raises(ValueError, match="unknown thread role"):
        ThreadPriorities().apply("gpu")


def test_worker_progress_tells_a_long_computation_from_a_blocked_thread():
    """Looping workers are healthy; inside working(), one burning CPU stays healthy past the loop
    window, one blocked on an event (no CPU) is stalled once busy_quiet_s passed; a stalled worker
    that loops again is healthy again."""
    progress = WorkerProgress(["spinner", "blocked"], max_age_s=0.3, busy_quiet_s=0.5)
    release, done = threading.Event(), threading.Event()

    def spinner():
        with progress.working("spinner"):
            t_end = time.monotonic() + 2.0  # bounded: 2 s of arithmetic
            x = 0
            while time.monotonic() < t_end:
                x += 1
        done.set()

    def blocked():
        with progress.working("blocked"):
            release.wait(5)
        progress.beat("blocked")

    threads = [threading.Thread(target=f) for f in (spinner, blocked)]
    for t in threads:
        t.start()
    try:
        time.sleep(0.2)
        assert progress.stalled() == {}
        time.sleep(1.2)  # past both windows
        stalled = progress.stalled()
        assert set(stalled) == {"blocked"} and "without using CPU" in stalled["blocked"], stalled
        release.set()
        time.sleep(0.05)
        assert "blocked" not in progress.stalled()
        assert done.wait(3)
        time.sleep(0.4)  # neither loops any more: both stalled, as a dead thread would be
        assert set(progress.stalled()) == {"spinner", "blocked"}
    finally:
        release.set()
        for t in threads:
            t.join(5)


def test_run_at_rate_counts_a_failing_step_and_keeps_going():
    stop, counters, calls = threading.Event(), Counter(), []

    def step():
        calls.append(1)
        if len(calls) == 2:
            raise RuntimeError("one bad update")
        if len(calls) == 4:
            stop.set()

    run_at_rate(step, 200.0, stop, counters, "test")
    assert len(calls) == 4 and counters["errors"] == 1

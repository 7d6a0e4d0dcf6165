"""Contract helpers for fuzz targets: a per-call time limit, an allocation bound, the finding type."""

import contextlib
import signal
import threading
import time
import tracemalloc

USE_ALARM = True
"""False where another owner of SIGALRM runs the process (atheris: libFuzzer's -timeout catches hangs)."""


class Finding(AssertionError):
    """An input broke a parser's contract (wrong exception type, hang, over-allocation, bad round trip)."""


class _Hang(BaseException):
    """Raised by the alarm inside a call that overran its time limit (BaseException: parsers can't eat it)."""


@contextlib.contextmanager
def time_limit(seconds: float, what: str):
    """Finding if the block runs longer than `seconds` (SIGALRM in the main thread, else elapsed time).

    An outer alarm (pytest-timeout's) is suspended meanwhile and re-armed with what was left of it."""
    use_alarm = USE_ALARM and threading.current_thread() is threading.main_thread()
    t0 = time.monotonic()
    if use_alarm:
        def on_alarm(signum, frame):
            raise _Hang()

        previous = signal.signal(signal.SIGALRM, on_alarm)
        outer_left, _ = signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    except _Hang:
        raise Finding(f"{what}: still running after {seconds} s (hang)") from None
    finally:
        if use_alarm:
            signal.setitimer(signal.ITIMER_REAL, 0)
            signal.signal(signal.SIGALRM, signal.SIG_DFL if previous is None else previous)
            if outer_left:
                signal.setitimer(signal.ITIMER_REAL, max(1e-3, outer_left - (time.monotonic() - t0)))
    elapsed = time.monotonic() - t0
    if elapsed > seconds:
        raise Finding(f"{what}: took {elapsed:.2f} s, limit {seconds} s")


@contextlib.contextmanager
def allocation_limit(max_bytes, what: str, enabled: bool = True):
    """Finding if the block's tracemalloc peak exceeds `max_bytes` (numpy buffers are traced too);
    max_bytes may be a callable, evaluated after the block (a bound that depends on the outcome)."""
    if not enabled:
        yield
        return
    started_here = not tracemalloc.is_tracing()
    if started_here:
        tracemalloc.start()
    tracemalloc.reset_peak()
    base = tracemalloc.get_traced_memory()[0]
    try:
        yield
    finally:
        peak = tracemalloc.get_traced_memory()[1] - base
        if started_here:
            tracemalloc.stop()
    bound = max_bytes() if callable(max_bytes) else max_bytes
    if peak > bound:
        raise Finding(f"{what}: allocated {peak} bytes at peak, bound {bound}")


def expect_only(error_types, what: str, call):
    """call(); returns its result, or None if it raised one of error_types with a message."""
    try:
        return call()
    except error_types as e:
        if not str(e).strip():
            raise Finding(f"{what}: {type(e).__name__} without a message") from e
        return None
    except Finding:
        raise
    except Exception as e:
        raise Finding(f"{what}: undocumented {type(e).__name__}: {e}") from e

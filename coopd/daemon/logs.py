"""coopd's log output: plain lines on a terminal or in a file, syslog-prefixed lines for journald.

Under systemd stderr is a stream to journald ($JOURNAL_STREAM names its device and inode). journald
reads a leading `<N>` on each line as the syslog priority (SyslogLevelPrefix=, on by default), so
`journalctl -p warning -u coopd` shows exactly coopd's WARNING, ERROR and CRITICAL lines. Every line
of a multi-line record (a traceback) carries the prefix: journald splits the stream on newlines.

Not systemd-python's JournalHandler: sd_journal_send holds the GIL while journald's socket is full,
which would stop every thread of the daemon (see coopd.daemon.notify for the same trap with
sd_notify). A write to the stream releases the GIL.
"""

import logging
import os
import sys

SYSLOG_PRIORITY = {
    logging.CRITICAL: 2,  # crit
    logging.ERROR: 3,  # err
    logging.WARNING: 4,  # warning
    logging.INFO: 6,  # info
    logging.DEBUG: 7,  # debug
}

PLAIN_FORMAT = "%(levelname)s %(name)s: %(message)s"


def syslog_priority(levelno: int) -> int:
    """The syslog priority of a logging level (custom levels take the next standard one below)."""
    for level in sorted(SYSLOG_PRIORITY, reverse=True):
        if levelno >= level:
            return SYSLOG_PRIORITY[level]
    return SYSLOG_PRIORITY[logging.DEBUG]


def stream_is_journal(stream, environ=None) -> bool:
    """True when `stream` is the journald stream systemd gave us ($JOURNAL_STREAM is "dev:ino").

    Compared with the file's device and inode, not merely present: a child that inherited the
    variable but writes elsewhere (a shell redirect) gets plain lines.
    """
    value = (os.environ if environ is None else environ).get("JOURNAL_STREAM", "")
    device, sep, inode = value.partition(":")
    if not sep or not device.isdigit() or not inode.isdigit():
        return False
    try:
        st = os.fstat(stream.fileno())
    except (AttributeError, OSError, ValueError):
        return False
    return (st.st_dev, st.st_ino) == (int(device), int(inode))


class JournalFormatter(logging.Formatter):
    """PLAIN_FORMAT with `<N>` (the record's syslog priority) before every line; journald adds the time."""

    def __init__(self):
        super().__init__(PLAIN_FORMAT)

    def format(self, record: logging.LogRecord) -> str:
        prefix = f"<{syslog_priority(record.levelno)}>"
        return "\n".join(prefix + line for line in super().format(record).split("\n"))


def formatter_for(stream, environ=None) -> logging.Formatter:
    """Journal lines for the journal stream (journald adds the time), timestamped lines elsewhere: a
    terminal, a file or a pipe (a log read after a run needs to say when each event happened)."""
    if stream_is_journal(stream, environ):
        return JournalFormatter()
    return logging.Formatter("%(asctime)s " + PLAIN_FORMAT)


def setup_logging(level: str, stream=None, environ=None) -> logging.Handler:
    """Route every logger to `stream` (stderr) at `level` with the format that stream needs."""
    stream = sys.stderr if stream is None else stream
    handler = logging.StreamHandler(stream)
    handler.setFormatter(formatter_for(stream, environ))
    root = logging.getLogger()
    root.handlers[:] = [handler]
    root.setLevel(level.upper())
    return handler

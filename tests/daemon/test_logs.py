"""Log lines: `<N>` syslog priorities when stderr is systemd's journal stream, timestamped lines otherwise."""

import logging
import os
import re
import sys
from pathlib import Path

import pytest

from coopd.daemon.logs import JournalFormatter, setup_logging, stream_is_journal, syslog_priority


@pytest.fixture
def root_logger():
    """The root logger, its handlers and level restored after the test."""
    root = logging.getLogger()
    saved = root.handlers[:], root.level
    yield root
    root.handlers[:] = saved[0]
    root.setLevel(saved[1])


def _journal_env(path: Path) -> dict:
    st = os.stat(path)
    return {"JOURNAL_STREAM": f"{st.st_dev}:{st.st_ino}"}


def test_syslog_priorities_of_the_logging_levels():
    assert [syslog_priority(level) for level in (logging.DEBUG, logging.INFO, logging.WARNING,
                                                 logging.ERROR, logging.CRITICAL)] == [7, 6, 4, 3, 2]
    assert syslog_priority(logging.WARNING + 5) == 4 and syslog_priority(1) == 7


def test_journal_stream_is_recognised_by_device_and_inode(tmp_path):
    mine, other = tmp_path / "mine", tmp_path / "other"
    with open(mine, "w") as stream, open(other, "w"):
        assert stream_is_journal(stream, _journal_env(mine))
        assert not stream_is_journal(stream, _journal_env(other))  # inherited variable, redirected stderr
        for value in ("", "12", "a:b", "1:2:3", ":"):
            assert not stream_is_journal(stream, {"JOURNAL_STREAM": value})
        assert not stream_is_journal(stream, {})


def test_every_line_of_a_record_carries_its_priority():
    try:
        raise ValueError("bad frame")
    except ValueError:
        record = logging.LogRecord("coopd.camera", logging.ERROR, __file__, 1, "camera %s", ("gone",),
                                   sys.exc_info())
    lines = JournalFormatter().format(record).split("\n")
    assert lines[0] == "<3>ERROR coopd.camera: camera gone"
    assert len(lines) > 3 and all(line.startswith("<3>") for line in lines)
    assert lines[-1] == "<3>ValueError: bad frame"


def test_setup_logging_picks_the_format_for_the_stream(tmp_path, root_logger):
    path = tmp_path / "stderr"
    with open(path, "w") as stream:
        setup_logging("info", stream, _journal_env(path))
        logging.getLogger("coopd.sharing").warning("peer %s refused: auth", "10.0.0.2")
        logging.getLogger("coopd.sharing").debug("not shown at info")
        setup_logging("info", stream, {})
        logging.getLogger("coopd.sharing").info("plain")
    journal, plain = path.read_text().splitlines()
    assert journal == "<4>WARNING coopd.sharing: peer 10.0.0.2 refused: auth"
    assert re.fullmatch(r"\d{4}-\d\d-\d\d \d\d:\d\d:\d\d,\d{3} INFO coopd.sharing: plain", plain), plain


def test_coopd_writes_prefixed_lines_to_its_journal_stream(tmp_path, monkeypatch, root_logger):
    """The daemon's own entry point: a start failure is an `<3>` line when stderr is the journal."""
    from coopd.daemon import main as daemon_main
    from coopd.daemon import service

    def refuse(config):
        raise OSError(f"control socket {config.daemon.control_socket} in use")

    monkeypatch.setattr(service, "Daemon", refuse)
    path = tmp_path / "stderr"
    with open(path, "w") as stderr:
        monkeypatch.setattr(sys, "stderr", stderr)
        monkeypatch.setenv("JOURNAL_STREAM", _journal_env(path)["JOURNAL_STREAM"])
        code = daemon_main.main(["--no-config", "--control-socket", str(tmp_path / "c.sock")])
    assert code == daemon_main.EXIT_START_FAILED
    expected = f"<3>ERROR coopd.daemon: cannot start: control socket {tmp_path}/c.sock in use\n"
    assert path.read_text() == expected

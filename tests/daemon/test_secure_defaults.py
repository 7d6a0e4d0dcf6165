"""Secure by default: a daemon that shares maps needs a swarm key, read with the documented decoder
(never cut short); an open server is an explicit opt-in, logged as a warning at every start."""

import pytest
from daemon_harness import swarm_key_file

from coopd.daemon.config import SharingConfig
from coopd.daemon.service import StartupError, swarm_key
from coopd.sharing import swarmkey


def test_no_key_refuses_to_start_with_the_fix_in_the_message():
    with pytest.raises(StartupError, match="coopctl key generate"):
        swarm_key(SharingConfig())


def test_open_is_an_explicit_opt_in_logged_as_a_warning(caplog):
    with caplog.at_level("WARNING", logger="coopd.daemon"):
        assert swarm_key(SharingConfig(open=True)) is None
    assert any("sharing is OPEN" in r.getMessage() and r.levelname == "WARNING" for r in caplog.records)


def test_the_daemon_reads_the_key_file_as_coopctl_key_check_does(tmp_path):
    path = swarm_key_file(tmp_path)  # coopctl's hex: format
    key = swarm_key(SharingConfig(swarm_key_file=str(path)))
    assert key == swarmkey.read_key_file(path) and len(key) == 32  # decoded, not the 69 text bytes
    with pytest.raises(StartupError, match="choose one"):
        swarm_key(SharingConfig(swarm_key_file=str(path), open=True))


@pytest.mark.parametrize("content, error", [
    ("x" * 5000, "larger than 4096 bytes"),  # was silently cut at 4096 bytes
    ("hex:" + "ab" * 5, "at least 16 bytes"),
    ("hex:not-hex-at-all-not-hex-at-all", "non-hexadecimal"),
    ("   \n", "is empty"),
])
def test_a_bad_key_file_refuses_to_start(tmp_path, content, error):
    path = tmp_path / "swarm.key"
    path.write_text(content)
    with pytest.raises(StartupError, match=error):
        swarm_key(SharingConfig(swarm_key_file=str(path)))


def test_the_sharing_settings_reach_the_receiver(tmp_path):
    from coopd.daemon.budget import MemoryBudget
    from coopd.daemon.config import from_dict
    from coopd.daemon.service import sharing_config

    path = swarm_key_file(tmp_path)
    cfg = from_dict({"sharing": {"swarm_key_file": str(path), "max_clock_skew_s": 60.0,
                                 "allowed_vehicles": [2, 3]}})
    out = sharing_config(cfg, MemoryBudget(512 << 20, baseline_bytes=0))
    assert out.max_epoch_ahead_s == 60.0 and out.allowed_vehicles == frozenset({2, 3})
    assert out.transport.swarm_key == swarmkey.read_key_file(path)


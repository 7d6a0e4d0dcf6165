"""systemd/coopd.service: `systemd-analyze verify` is clean, and the unit agrees with the config.

verify needs ExecStart's binary to exist, and `coopd` is not installed in the test environment:
the test verifies a copy of the unit whose ExecStart points at a stand-in script in a temp dir
(everything else byte-identical).
"""

import os
import shutil
import subprocess
from pathlib import Path

import pytest

from coopd.daemon.config import Config, load_config

ROOT = Path(__file__).resolve().parents[2]
UNIT = ROOT / "systemd" / "coopd.service"
ANALYZE = shutil.which("systemd-analyze")
needs_analyze = pytest.mark.skipif(
    ANALYZE is None, reason="systemd-analyze not installed (Debian package systemd)"
)


def unit_with_standin(tmp_path: Path, text: str | None = None) -> Path:
    standin = tmp_path / "coopd"
    standin.write_text("#!/bin/sh\nexit 0\n")
    standin.chmod(0o755)
    text = UNIT.read_text() if text is None else text
    assert "ExecStart=/opt/coopd/bin/coopd " in text
    unit = tmp_path / "coopd.service"
    unit.write_text(text.replace("ExecStart=/opt/coopd/bin/coopd ", f"ExecStart={standin} "))
    return unit


def verify(unit: Path) -> tuple[int, list[str]]:
    """Exit code and the complaints about our unit (verify exits 0 on unknown keys, so read them)."""
    r = subprocess.run([ANALYZE, "verify", "--man=no", str(unit)], capture_output=True, text=True, timeout=60)
    lines = [ln for ln in (r.stdout + r.stderr).splitlines() if unit.name in ln]
    return r.returncode, lines


@needs_analyze
def test_systemd_analyze_verify_is_clean(tmp_path):
    code, complaints = verify(unit_with_standin(tmp_path))
    assert code == 0 and complaints == []


@needs_analyze
@pytest.mark.parametrize(
    "change",
    [
        ("Type=notify", "Type=notifyy"),
        ("WatchdogSec=10", "WatchdogSec=10\nFooBar=1"),
        ("ExecStart=/opt/coopd/bin/coopd ", "ExecStart=/nonexistent/coopd "),
    ],
)
def test_verify_check_catches_broken_units(tmp_path, change):
    text = UNIT.read_text().replace(*change)
    if "nonexistent" in change[1]:
        unit = tmp_path / "coopd.service"
        unit.write_text(text)
    else:
        unit = unit_with_standin(tmp_path, text)
    code, complaints = verify(unit)
    assert code != 0 or complaints


def service_section() -> dict[str, list[str]]:
    values: dict[str, list[str]] = {}
    section = None
    for line in UNIT.read_text().splitlines():
        line = line.strip()
        if line.startswith("["):
            section = line
        elif line and not line.startswith("#") and section == "[Service]":
            key, value = line.split("=", 1)
            values.setdefault(key, []).append(value)
    return values


def test_unit_settings_required_by_the_design():
    s = service_section()
    for key, value in [
        ("Type", "notify"),
        ("NotifyAccess", "main"),
        ("Restart", "on-failure"),
        ("RuntimeDirectory", "coopd"),
        ("StateDirectory", "coopd"),
        ("ProtectSystem", "strict"),
        ("NoNewPrivileges", "yes"),
        ("ProtectHome", "yes"),
        ("PrivateTmp", "yes"),
        ("RestrictAddressFamilies", "AF_UNIX AF_INET AF_INET6 AF_NETLINK"),
    ]:
        assert s.get(key) == [value], key
    assert int(s["WatchdogSec"][0]) > 0
    assert "MemoryDenyWriteExecute" not in s  # numba JIT needs writable+executable memory
    assert s["ExecStart"] == ["/opt/coopd/bin/coopd --config /etc/coopd/coopd.toml"]
    env = dict(v.split("=", 1) for v in s["Environment"])
    assert env["NUMBA_CACHE_DIR"].startswith("/var/cache/" + s["CacheDirectory"][0] + "/")
    # the kernel cache is code the daemon loads: nobody but its user may write there
    assert int(s["UMask"][0], 8) & 0o022 == 0o022
    assert int(s["CacheDirectoryMode"][0], 8) & 0o022 == 0


def test_default_config_paths_match_the_unit_directories():
    s = service_section()
    c = load_config(ROOT / "etc" / "coopd.toml")
    assert c == Config.defaults()
    assert c.daemon.state_dir == "/var/lib/" + s["StateDirectory"][0]
    assert os.path.dirname(c.daemon.control_socket) == "/run/" + s["RuntimeDirectory"][0]
    assert c.daemon.memory_mb * 2**20 < 2**30  # MemoryMax=1G stays above the budget


@needs_analyze
def test_security_exposure_is_low(tmp_path):
    r = subprocess.run(
        [ANALYZE, "security", "--offline=true", "--no-pager", str(unit_with_standin(tmp_path))],
        capture_output=True,
        text=True,
        timeout=60,
    )
    last = [ln for ln in r.stdout.splitlines() if "Overall exposure level" in ln]
    if r.returncode != 0 or not last:
        pytest.skip(f"systemd-analyze security --offline unavailable: {r.stderr.strip()[:200]}")
    score = float(last[0].split(":")[1].split()[0])
    assert score <= 3.0, last[0]


def test_sysusers_file_declares_the_user_and_group():
    text = (ROOT / "systemd" / "coopd.sysusers").read_text()
    entries = [ln.split()[:2] for ln in text.splitlines() if ln and not ln.startswith("#")]
    assert ["g", "coopd"] in entries and ["u", "coopd"] in entries

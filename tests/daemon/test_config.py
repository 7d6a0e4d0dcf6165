"""coopd.toml: defaults, the documented default file, and errors that name the key."""

import dataclasses
import re
import tomllib
from pathlib import Path

import pytest

from coopd.daemon.config import Config, ConfigError, config_keys, load_config, parse_config
from coopd.mapping import MapperConfig

ETC = Path(__file__).resolve().parents[2] / "etc" / "coopd.toml"


def test_default_file_equals_defaults():
    assert load_config(ETC) == Config.defaults()
    assert parse_config("") == Config.defaults()


def test_mapping_defaults_come_from_mapper_config():
    assert Config.defaults().mapping == MapperConfig()
    assert isinstance(load_config(ETC).mapping, MapperConfig)


def test_every_key_is_in_the_default_file_with_a_comment_above():
    lines = ETC.read_text().splitlines()
    section = ""
    seen = {}
    for i, line in enumerate(lines):
        m = re.match(r"^\[([a-z.]+)\]$", line)
        if m:
            section = m.group(1)
            continue
        m = re.match(r"^([a-z_0-9]+) = ", line)
        if m:
            seen[f"{section}.{m.group(1)}"] = i
    for key, _, _doc in config_keys():
        assert key in seen, f"{key} missing from etc/coopd.toml"
        assert lines[seen[key] - 1].startswith("# "), f"{key} has no comment line above it"
    assert set(seen) == {k for k, _, _ in config_keys()}


def test_every_own_key_has_a_doc():
    for key, _, doc in config_keys():
        if not key.startswith("mapping."):
            assert doc, key


def test_file_values_override_defaults(tmp_path):
    path = tmp_path / "c.toml"
    path.write_text(
        "[vehicle]\nid = 7\ncamera_mount_m = [0.1, 0, -0.05]\n[sharing]\n"
        'peers = ["10.42.0.1-20", "drone3:7401"]\n[mapping]\nresolution = 0.2\n'
        "[mapping.growth]\nmax_cells = 1000000\n"
    )
    c = load_config(path)
    assert c.vehicle.id == 7 and c.vehicle.camera_mount_m == (0.1, 0.0, -0.05)
    assert c.sharing.peers == ("10.42.0.1-20", "drone3:7401")
    assert c.mapping.resolution == 0.2 and c.mapping.growth.max_cells == 1_000_000
    assert c.daemon == Config.defaults().daemon
    with pytest.raises(dataclasses.FrozenInstanceError):
        c.vehicle.id = 3


BAD = [
    ("[vehicle]\nid = 0", "vehicle.id", "outside"),
    ("[vehicle]\nid = 1.5", "vehicle.id", "integer"),
    ("[vehicle]\nid = true", "vehicle.id", "integer"),
    ("[vehicle]\nmavlink = 'serial0'", "vehicle.mavlink", "MAVLink connection"),
    ("[vehicle]\nmavlink = 'udpin:0.0.0.0:99999'", "vehicle.mavlink", "outside"),
    ("[vehicle]\ncamera_mount_m = [0, 0]", "vehicle.camera_mount_m", "exactly 3"),
    ("[vehicle]\ncamera_mount_m = [0, 'a', 0]", "vehicle.camera_mount_m[1]", "number"),
    ("[vehicle]\nlink_timeout_s = nan", "vehicle.link_timeout_s", "finite"),
    ("[camera]\nsource = 'usb'", "camera.source", "camera source"),
    ("[camera]\nsource = 'socket:relative.sock'", "camera.source", "absolute"),
    ("[mapping]\nresolution = 50.0", "mapping.resolution", "resolution"),
    ("[mapping]\nmax_range = 0.1", "mapping", "range"),
    ("[mapping]\ntraversal = 'dda'", "mapping.traversal", "traversal"),
    ("[mapping]\nbeyond_max_range = 'ignore'", "mapping.beyond_max_range", "one of"),
    ("[mapping]\nthreads = '2'", "mapping.threads", "integer"),
    ("[mapping.growth]\nmargin = -1", "mapping.growth", "growth"),
    ("[sharing]\nport = 70000", "sharing.port", "outside"),
    ("[sharing]\nlisten_host = 'everywhere'", "sharing.listen_host", "IP address"),
    ("[sharing]\npeers = ['10.0.0.1-10.0.255.255']", "sharing.peers", "more than"),
    ("[sharing]\npeers = ['10.0.0.9-1']", "sharing.peers", "backwards"),
    ("[sharing]\npeers = 'a,b'", "sharing.peers", "list"),
    ("[sharing]\npeer_ports = []", "sharing.peer_ports", "at least one"),
    ("[sharing]\nswarm_key_file = 'key'", "sharing.swarm_key_file", "absolute"),
    ("[sharing]\nrelay = 1", "sharing.relay", "true or false"),
    ("[merging]\nperiod_s = 0", "merging.period_s", "outside"),
    ("[obstacles]\nrate_hz = 0.5", "obstacles.rate_hz", "outside"),
    ("[obstacles]\nmax_distance_m = 40", "obstacles.max_distance_m", "outside"),
    ("[obstacles]\nmin_distance_m = 2.0\nmax_distance_m = 1.0", "obstacles.min_distance_m", "not below"),
    ("[obstacles]\nband_below_m = -0.1", "obstacles.band_below_m", "outside"),
    ("[obstacles]\nenabled = 'yes'", "obstacles.enabled", "true or false"),
    ("[viewer]\nport = 0", "viewer.port", "outside"),
    ("[viewer]\nhost = 'localhost'", "viewer.host", "IP address"),
    ("[viewer]\nrate_hz = 100", "viewer.rate_hz", "outside"),
    ("[viewer]\nenabled = true\nhost = '0.0.0.0'", "viewer.host", "not loopback"),
    ("[viewer]\nenabled = true\nhost = '10.1.2.3'\nopen = 'yes'", "viewer.open", "true or false"),
    ("[viewer]\ncolour = 'rainbow'", "viewer.colour", "one of"),
    ("[viewer]\nenabled = 'yes'", "viewer.enabled", "true or false"),
    ("[daemon]\nmemory_mb = 8", "daemon.memory_mb", "outside"),
    ("[daemon]\nlog_level = 'verbose'", "daemon.log_level", "one of"),
    ("[daemon]\nstate_dir = 'var/lib'", "daemon.state_dir", "absolute"),
    ("[daemon]\ncontrol_socket = '/run/" + "x" * 100 + "'", "daemon.control_socket", "longer than"),
    ("daemon = 3", "daemon", "table"),
]


@pytest.mark.parametrize("text,key,words", BAD, ids=[b[1] + ":" + b[2] for b in BAD])
def test_bad_values_name_the_key(text, key, words):
    with pytest.raises(ConfigError) as e:
        parse_config(text)
    assert e.value.key == key
    assert str(e.value).startswith(f"{key}: ")
    assert words in str(e.value)


UNKNOWN = [
    ("[vehicle]\nidd = 3", "vehicle.idd"),
    ("[mapping]\nresolutoin = 0.1", "mapping.resolutoin"),
    ("[mapping.growth]\nmax = 1", "mapping.growth.max"),
    ("[deamon]\nmemory_mb = 100", "deamon"),
    ("verbose = true", "verbose"),
]


@pytest.mark.parametrize("text,key", UNKNOWN)
def test_unknown_keys_are_errors(text, key):
    with pytest.raises(ConfigError, match="unknown key") as e:
        parse_config(text)
    assert e.value.key == key


def test_syntax_and_file_errors(tmp_path):
    with pytest.raises(ConfigError, match="not valid TOML"):
        parse_config("[vehicle\nid = 1")
    p = tmp_path / "bin.toml"
    p.write_bytes(b"\xff\xfe")
    with pytest.raises(ConfigError, match="not UTF-8"):
        load_config(p)
    with pytest.raises(FileNotFoundError):
        load_config(tmp_path / "missing.toml")
    big = tmp_path / "big.toml"
    big.write_bytes(b"#" * (2 << 20))
    with pytest.raises(ConfigError, match="larger than"):
        load_config(big)


def test_default_file_is_plain_toml():
    assert set(tomllib.loads(ETC.read_text())) == {f.name for f in dataclasses.fields(Config)}


def test_viewer_is_off_by_default_on_loopback_and_turned_on_by_the_file():
    viewer = Config.defaults().viewer
    assert viewer.enabled is False and viewer.host == "127.0.0.1" and viewer.port == 8765
    c = parse_config("[viewer]\nenabled = true\nhost = '::1'\nport = 9000\ncolour = 'source'\n")
    assert c.viewer.enabled and c.viewer.host == "::1" and c.viewer.port == 9000
    assert c.viewer.colour == "source"
    assert viewer.open is False  # off loopback only when the operator opts out of authentication
    c = parse_config("[viewer]\nenabled = true\nhost = '0.0.0.0'\nopen = true\n")
    assert c.viewer.host == "0.0.0.0" and c.viewer.open
    assert parse_config("[viewer]\nhost = '0.0.0.0'\n").viewer.host == "0.0.0.0"  # not served: no risk


def test_obstacles_are_off_by_default_and_turned_on_by_the_file():
    assert Config.defaults().obstacles.enabled is False
    c = parse_config("[obstacles]\nenabled = true\nrate_hz = 20\nband_above_m = 0.5\n")
    assert c.obstacles.enabled and c.obstacles.rate_hz == 20.0 and c.obstacles.band_above_m == 0.5
    assert c.obstacles.max_distance_m == 5.0

"""coopd.toml: one plain TOML file loaded into frozen dataclasses, every value checked.

    config = load_config("/etc/coopd/coopd.toml")     # or Config.defaults()
    config.vehicle.id, config.mapping (a coopd.mapping.MapperConfig), config.daemon.memory_mb

Errors name the key (`sharing.port: 70000 is outside 1..65535`); unknown keys and sections are
errors too, so a typo never silently falls back to a default. The documented default file is
etc/coopd.toml; tests check that it lists every key with its default value.
"""

import dataclasses
import ipaddress
import math
import re
import tomllib
import typing
from dataclasses import dataclass, field
from pathlib import Path

from coopd.camera.realsense import RealSenseConfig
from coopd.camera.socket_source import DEFAULT_CAMERA_SOCKET
from coopd.daemon.control import DEFAULT_CONTROL_SOCKET, MAX_SOCKET_PATH
from coopd.mapping import MapperConfig
from coopd.sharing.discovery import parse_targets
from coopd.sharing.zenoh_link import ZenohSettings
from coopd.vehicle.connection import parse_connection

DEFAULT_CONFIG_PATH = Path("/etc/coopd/coopd.toml")
MAX_CONFIG_BYTES = 1 << 20
LOG_LEVELS = ("debug", "info", "warning", "error")


class ConfigError(ValueError):
    """A configuration problem; `key` is the dotted key (or section) it concerns."""

    def __init__(self, key: str, problem: str):
        super().__init__(f"{key}: {problem}" if key else problem)
        self.key = key
        self.problem = problem


# ---------------------------------------------------------------------------------- value checks
def _between(lo, hi, unit: str = ""):
    def check(v):
        if isinstance(v, float) and not math.isfinite(v):
            return f"{v} is not a finite number"
        if not lo <= v <= hi:
            return f"{v}{unit} is outside {lo}..{hi}{unit}"
        return None

    return check


def _each(check):
    def each(values):
        for v in values:
            problem = check(v)
            if problem:
                return problem
        return None

    return each


def _length(n: int, inner=None):
    def check(values):
        if len(values) != n:
            return f"needs exactly {n} values, got {len(values)}"
        return _each(inner)(values) if inner else None

    return check


def _absolute_path(allow_empty: bool = False):
    def check(v):
        if allow_empty and v == "":
            return None
        if not v.startswith("/") or "\0" in v:
            return f"{v!r} must be an absolute path"
        return None

    return check


def _socket_path(v: str):
    problem = _absolute_path()(v)
    if problem is None and len(v.encode()) > MAX_SOCKET_PATH:
        problem = f"{v!r} is longer than {MAX_SOCKET_PATH} bytes (unix socket path limit)"
    return problem


def _port_ok(text: str) -> bool:
    return text.isdigit() and 1 <= int(text) <= 65535


def _mavlink_connection(v: str):
    """The transport's own parser (coopd.vehicle.connection): what passes here, the link opens."""
    try:
        parse_connection(v)
    except ValueError as e:
        return str(e)
    return None


def _camera_source(v: str):
    if v == "realsense" or re.fullmatch(r"realsense:[A-Za-z0-9_-]{1,64}", v):
        return None
    if v.startswith("socket:"):
        return _absolute_path()(v[len("socket:") :])
    m = re.fullmatch(r"tcp:([^:\s]+):(\d+)", v)
    if m:
        return None if _port_ok(m.group(2)) else f"port {m.group(2)} of {v!r} is outside 1..65535"
    return f"{v!r} is not a camera source (socket:/PATH, tcp:HOST:PORT, realsense or realsense:SERIAL)"


def _ip_address(v: str):
    try:
        ipaddress.ip_address(v)
    except ValueError:
        return f"{v!r} is not an IP address"
    return None


def _peer_spec(spec: str):
    """One peers entry, checked by the parser the sharing service expands it with."""
    try:
        parse_targets([spec], (1,))
    except ValueError as e:
        return str(e)
    return None


def _one_of(*choices):
    def check(v):
        return None if v in choices else f"{v!r} is not one of {', '.join(choices)}"

    return check


def _key(doc: str, default, check=None):
    """A config key: its default, a one-line doc and an optional check returning a problem or None."""
    if isinstance(default, (list, tuple)):
        value = tuple(default)
        return field(default_factory=lambda: value, metadata={"doc": doc, "check": check})
    return field(default=default, metadata={"doc": doc, "check": check})


# -------------------------------------------------------------------------------------- sections
@dataclass(frozen=True)
class VehicleConfig:
    """[vehicle]: who we are and how to reach the flight controller."""

    id: int = _key("MAVLink system id of this vehicle, also its id in the swarm", 1, _between(1, 255))
    mavlink: str = _key("flight-controller connection string", "udpin:0.0.0.0:14540", _mavlink_connection)
    signing_key_file: str = _key(
        "MAVLink 2 signing key file (64 hex characters); empty: no signing", "",
        _absolute_path(allow_empty=True),
    )
    link_timeout_s: float = _key(
        "no MAVLink message for this long: link lost", 1.5, _between(0.1, 60.0, " s")
    )
    odometry_timeout_s: float = _key(
        "no odometry for this long: odometry stale, mapping pauses", 0.5, _between(0.05, 60.0, " s")
    )
    odometry_rate_hz: float = _key(
        "odometry stream rate requested from the FC", 30.0, _between(1.0, 500.0, " Hz")
    )
    camera_mount_m: tuple[float, ...] = _key(
        "camera position on the body (x fwd, y left, z up), metres",
        (0.0, 0.0, 0.0),
        _length(3, _between(-10.0, 10.0, " m")),
    )
    camera_mount_rpy_deg: tuple[float, ...] = _key(
        "camera roll, pitch, yaw relative to a forward-looking camera, degrees",
        (0.0, 0.0, 0.0),
        _length(3, _between(-360.0, 360.0, " deg")),
    )


@dataclass(frozen=True)
class CameraConfig:
    """[camera]: where depth frames come from."""

    source: str = _key(
        "depth source: socket:/PATH, tcp:HOST:PORT, realsense",
        "socket:" + DEFAULT_CAMERA_SOCKET,
        _camera_source,
    )
    stall_timeout_s: float = _key(
        "no byte from the camera for this long: reconnect", 2.0, _between(0.1, 60.0, " s")
    )
    max_payload_bytes: int = _key(
        "largest depth frame accepted", 8 * 1024 * 1024, _between(1024, 256 * 1024 * 1024, " B")
    )
    pose_wait_s: float = _key(
        "a frame newer than the newest pose waits this long for odometry", 0.1, _between(0.0, 1.0, " s")
    )
    realsense: RealSenseConfig = field(default_factory=RealSenseConfig)


@dataclass(frozen=True)
class SharingConfig:
    """[sharing]: maps exchanged with peers over MTP/TCP (thesis §7.3)."""

    enabled: bool = _key("share maps at all", True)
    listen_host: str = _key("address the map server listens on", "0.0.0.0", _ip_address)
    port: int = _key("TCP port of the map server", 7400, _between(1, 65535))
    peers: tuple[str, ...] = _key(
        "peers to scan: 'HOST', 'HOST:PORT', '10.42.0.1-10.42.0.20', '[fd00::7]:7401'", (), _each(_peer_spec)
    )
    peer_ports: tuple[int, ...] = _key(
        "ports scanned on peers without their own", (7400,), _each(_between(1, 65535))
    )
    scan_period_s: float = _key("seconds between discovery scans", 2.0, _between(0.1, 3600.0, " s"))
    grace_period_s: float = _key("a peer unseen this long is dropped", 30.0, _between(1.0, 86400.0, " s"))
    block_size: int = _key(
        "MTP block size in bytes, same on every vehicle", 4096, _between(64, 1 << 20, " B")
    )
    swarm_key_file: str = _key(
        "file holding the shared swarm key (coopctl key generate); empty: none (then open must be true)", "",
        _absolute_path(allow_empty=True)
    )
    open: bool = _key(
        "without a swarm key: accept maps from any host (thesis interop); false: a key is required", False
    )
    max_map_bytes: int = _key("largest received map message", 64 << 20, _between(1024, 1 << 30, " B"))
    max_map_cells: int = _key("largest received map, in cells", 100_000_000, _between(1, 400_000_000))
    relay: bool = _key("also forward maps received from others (multi-hop)", False)
    deltas: bool = _key(
        "send our map to peers that read deltas as the bricks changed since the version they hold", True
    )
    max_clock_skew_s: float = _key(
        "a received map version whose epoch is further ahead of our clock is refused", 300.0,
        _between(1.0, 1e9, " s")
    )
    allowed_vehicles: tuple[int, ...] = _key(
        "vehicle ids whose maps are accepted; empty: any id 1..255", (), _each(_between(1, 255))
    )
    transport: str = _key("'mtp' (the thesis protocol over TCP), 'zenoh' ([sharing.zenoh], the zenoh extra) "
                          "or 'both'", "mtp", _one_of("mtp", "zenoh", "both"))
    zenoh: ZenohSettings = field(default_factory=ZenohSettings)

    def __post_init__(self):
        if not self.peer_ports:
            raise ConfigError("sharing.peer_ports", "needs at least one port")


@dataclass(frozen=True)
class MergingConfig:
    """[merging]: building the global map from the local and received maps."""

    enabled: bool = _key("merge at all", True)
    period_s: float = _key("seconds between merges", 10.0, _between(0.5, 86400.0, " s"))
    on_receive: bool = _key("also merge as soon as a changed map arrives", True)
    distributed: bool = _key(
        "publish our merge results and use peers' as hints (false: own warm start only)", True
    )
    defer_full_s: float = _key(
        "distributed: seconds a map's full search waits for a lower vehicle id's result; 0: never",
        60.0, _between(0.0, 3600.0, " s"),
    )
    vouched: bool = _key(
        "distributed: a map a peer merged on exactly the map versions we hold is placed by its edge, "
        "checked, not refined (false: refined here too, about ten times the CPU per map)", True
    )
    search_threads: int = _key(
        "full searches of maps merged here for the first time run this many at a time (their fits are "
        "held provisional, so the results are those of one at a time)", 2, _between(1, 8, "")
    )
    recheck_growth: float = _key(
        "search a merged map again, its transform competing, once the pair's known cells grew this much",
        1.3, _between(1.05, 100.0, "x"),
    )
    confirm_before_fusing: bool = _key(
        "hold a newly found fit out of the global map until a recheck finds it again or the maps settle",
        True,
    )


@dataclass(frozen=True)
class ObstaclesConfig:
    """[obstacles]: the map around the vehicle sent to the FC as MAVLink OBSTACLE_DISTANCE."""

    enabled: bool = _key("always send OBSTACLE_DISTANCE to the FC", False)
    when_fc_asks: bool = _key("send it while the FC is set up to use it (PX4 CP_DIST > 0, ArduPilot "
                              "PRX1_TYPE = 2), read from its parameters", True)
    rate_hz: float = _key("messages per second", 10.0, _between(1.0, 50.0, " Hz"))
    min_distance_m: float = _key(
        "nearer cells are the vehicle itself and are left out", 0.3, _between(0.05, 5.0, " m")
    )
    max_distance_m: float = _key(
        "range read around the vehicle; free up to it reads max + 1 cm", 5.0, _between(0.5, 30.0, " m")
    )
    band_below_m: float = _key(
        "the band of cells read reaches this far below the vehicle", 0.3, _between(0.0, 5.0, " m")
    )
    band_above_m: float = _key(
        "the band of cells read reaches this far above the vehicle", 0.3, _between(0.0, 5.0, " m")
    )

    def __post_init__(self):
        if self.min_distance_m >= self.max_distance_m:
            raise ConfigError("obstacles.min_distance_m",
                              f"{self.min_distance_m} m is not below max_distance_m {self.max_distance_m} m")


@dataclass(frozen=True)
class ViewerConfig:
    """[viewer]: a live view of the map for the Foxglove app (the foxglove-sdk extra), off by default."""

    enabled: bool = _key("serve the live view (the viewer extra; off unless the file turns it on)", False)
    host: str = _key("address the viewer listens on; another than loopback needs open = true", "127.0.0.1",
                     _ip_address)
    open: bool = _key("serve an address other than loopback (the Foxglove protocol has no authentication: "
                      "anyone who reaches it sees the map)", False)
    port: int = _key("WebSocket port of the viewer", 8765, _between(1, 65535))
    rate_hz: float = _key("map, pose and status updates per second", 1.0, _between(0.1, 10.0, " Hz"))
    colour: str = _key("occupied cells coloured by height or by source (own map or peers')", "height",
                       _one_of("height", "source"))
    record_dir: str = _key("record the same channels to an MCAP file per start here; empty: no recording",
                           "", _absolute_path(allow_empty=True))
    record_max_mb: int = _key("a recording stops at this size, MiB", 1024, _between(1, 1 << 20, " MiB"))

    def __post_init__(self):
        if self.enabled and not self.open and not ipaddress.ip_address(self.host).is_loopback:
            raise ConfigError("viewer.host", f"{self.host} is not loopback and the Foxglove protocol has no "
                              "authentication: keep it on loopback (ssh tunnel) or set viewer.open = true")


@dataclass(frozen=True)
class DaemonConfig:
    """[daemon]: process-wide settings."""

    memory_mb: int = _key("memory budget of the whole process (RSS), MiB", 512, _between(64, 1 << 20, " MiB"))
    state_dir: str = _key(
        "checkpoints live here (systemd StateDirectory)", "/var/lib/coopd", _absolute_path()
    )
    control_socket: str = _key(
        "unix socket coopctl talks to (in the RuntimeDirectory)", DEFAULT_CONTROL_SOCKET, _socket_path
    )
    control_max_clients: int = _key("coopctl connections served at once", 8, _between(1, 256))
    control_timeout_s: float = _key(
        "a coopctl request must arrive within this time", 5.0, _between(0.1, 300.0, " s")
    )
    checkpoint_period_s: float = _key(
        "seconds between checkpoints; 0: only on shutdown", 60.0, _between(0.0, 86400.0, " s")
    )
    checkpoint_keep: int = _key(
        "checkpoints kept per map (the newest valid one is loaded)", 3, _between(1, 100)
    )
    log_level: str = _key("debug, info, warning or error", "info", _one_of(*LOG_LEVELS))


@dataclass(frozen=True)
class Config:
    """The whole coopd.toml."""

    vehicle: VehicleConfig = field(default_factory=VehicleConfig)
    camera: CameraConfig = field(default_factory=CameraConfig)
    mapping: MapperConfig = field(default_factory=MapperConfig)
    sharing: SharingConfig = field(default_factory=SharingConfig)
    merging: MergingConfig = field(default_factory=MergingConfig)
    obstacles: ObstaclesConfig = field(default_factory=ObstaclesConfig)
    viewer: ViewerConfig = field(default_factory=ViewerConfig)
    daemon: DaemonConfig = field(default_factory=DaemonConfig)

    @classmethod
    def defaults(cls) -> "Config":
        return cls()


# ---------------------------------------------------------------------------------------- loading
def load_config(path=DEFAULT_CONFIG_PATH) -> Config:
    """The Config in a TOML file; raises ConfigError (naming the key) or OSError."""
    path = Path(path)
    with open(path, "rb") as f:
        data = f.read(MAX_CONFIG_BYTES + 1)
    if len(data) > MAX_CONFIG_BYTES:
        raise ConfigError("", f"{path}: larger than {MAX_CONFIG_BYTES} bytes")
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as e:
        raise ConfigError("", f"{path}: not UTF-8 ({e})") from e
    return parse_config(text)


def parse_config(text: str) -> Config:
    """The Config described by TOML text; missing keys take their defaults."""
    try:
        table = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise ConfigError("", f"not valid TOML: {e}") from e
    return from_dict(table)


def from_dict(table: dict) -> Config:
    """The Config described by nested dicts (as tomllib returns them)."""
    return _build(Config, table, "")


def _build(cls, table, prefix: str):
    if not isinstance(table, dict):
        raise ConfigError(prefix, f"must be a table, got {_type_name(table)}")
    hints = typing.get_type_hints(cls)
    known = {f.name: f for f in dataclasses.fields(cls) if f.init}
    for name in table:
        if name not in known:
            where = f"[{prefix}]" if prefix else "the top level"
            raise ConfigError(_join(prefix, name), f"unknown key in {where} (known: {', '.join(known)})")
    kwargs = {}
    for name, value in table.items():
        key = _join(prefix, name)
        kwargs[name] = _convert(hints[name], value, key)
        check = known[name].metadata.get("check")
        problem = check(kwargs[name]) if check else None
        if problem:
            raise ConfigError(key, problem)
    try:
        return cls(**kwargs)
    except ConfigError:
        raise
    except (ValueError, TypeError) as e:
        # the key the message starts with ("tls_root_ca: ..."), else the one key it names
        named = ([n for n in known if str(e).startswith(f"{n}:")]
                 or [n for n in known if re.search(rf"\b{re.escape(n)}\b", str(e))])
        raise ConfigError(_join(prefix, named[0]) if len(named) == 1 else prefix, str(e)) from e


def _convert(kind, value, key: str):
    if dataclasses.is_dataclass(kind):
        return _build(kind, value, key)
    origin = typing.get_origin(kind)
    if origin is tuple:
        if not isinstance(value, list):
            raise ConfigError(key, f"must be a list, got {_type_name(value)}")
        inner = typing.get_args(kind)[0]
        return tuple(_convert(inner, v, f"{key}[{i}]") for i, v in enumerate(value))
    if kind is bool:
        if not isinstance(value, bool):
            raise ConfigError(key, f"must be true or false, got {_type_name(value)}")
        return value
    if kind is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(key, f"must be an integer, got {_type_name(value)}")
        return value
    if kind is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(key, f"must be a number, got {_type_name(value)}")
        if not math.isfinite(value):
            raise ConfigError(key, f"{value} is not a finite number")
        return float(value)
    if kind is str:
        if not isinstance(value, str):
            raise ConfigError(key, f"must be a string, got {_type_name(value)}")
        return value
    raise ConfigError(key, f"unsupported setting type {kind}")


def _join(prefix: str, name: str) -> str:
    return f"{prefix}.{name}" if prefix else name


def _type_name(value) -> str:
    return {
        dict: "a table",
        list: "a list",
        str: "a string",
        bool: "a boolean",
        int: "an integer",
        float: "a number",
    }.get(type(value), type(value).__name__)


def config_keys(cls=Config, prefix: str = ""):
    """(dotted key, default value, doc) of every leaf key, in file order."""
    hints = typing.get_type_hints(cls)
    instance = cls()
    for f in dataclasses.fields(cls):
        if not f.init:
            continue
        key = _join(prefix, f.name)
        if dataclasses.is_dataclass(hints[f.name]):
            yield from config_keys(hints[f.name], key)
        else:
            yield key, getattr(instance, f.name), f.metadata.get("doc", "")


def as_dict(config) -> dict:
    """The config as nested plain data (tuples as lists), e.g. for `coopctl status --json`."""
    out = {}
    for f in dataclasses.fields(config):
        value = getattr(config, f.name)
        if dataclasses.is_dataclass(value):
            out[f.name] = as_dict(value)
        elif isinstance(value, tuple):
            out[f.name] = list(value)
        else:
            out[f.name] = value
    return out

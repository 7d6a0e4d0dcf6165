"""MAVLink connection strings: the one parser behind `coopd --check-config` and the link's transports.

pymavlink forms: `udpin:HOST:PORT` (listen), `udp:HOST:PORT` (= udpin), `udpout:HOST:PORT` (send to),
`tcp:HOST:PORT` (connect), `tcpin:HOST:PORT` (listen for one connection), `/dev/DEVICE[,BAUD]`,
`serial:/dev/DEVICE[:BAUD]`. MAVSDK URLs: `udpin://[HOST]:PORT`, `udp://[HOST]:PORT` (= udpin),
`udpout://HOST:PORT`, `tcp://HOST:PORT` and `tcpout://HOST:PORT` (connect), `tcpin://[HOST]:PORT`,
`serial:///dev/DEVICE[:BAUD]`. HOST is an IPv4 address, an IPv6 address in brackets (`[::1]`) or a
host name; a listening form without HOST listens on every IPv4 interface. A serial port without a
baud rate runs at DEFAULT_BAUD.
"""

from __future__ import annotations

import ipaddress
import re
from dataclasses import dataclass

DEFAULT_BAUD = 57600
"""The usual telemetry-port rate (ArduPilot's SERIALn_BAUD default, MAVSDK's serial default)."""
BAUD_RANGE = (50, 20_000_000)
MAX_TEXT = 256
SCHEMES = {
    "udpin": "udpin", "udp": "udpin", "udpout": "udpout", "tcp": "tcp", "tcpout": "tcp", "tcpin": "tcpin"
}
"""Scheme as written -> Endpoint kind (udp: and udp:// listen, in pymavlink as in MAVSDK)."""
LISTENING = ("udpin", "tcpin")
FORMS = (
    "udpin:HOST:PORT, udp:HOST:PORT, udpout:HOST:PORT, tcp:HOST:PORT, tcpin:HOST:PORT, "
    "/dev/DEVICE[,BAUD], serial:/dev/DEVICE[:BAUD], or the MAVSDK URLs udpin://[HOST]:PORT, "
    "udp://[HOST]:PORT, udpout://HOST:PORT, tcp://HOST:PORT, tcpin://[HOST]:PORT, "
    "serial:///dev/DEVICE[:BAUD]"
)
_LABEL = r"[A-Za-z0-9]([A-Za-z0-9-]{0,62})"
_HOSTNAME = re.compile(rf"(?=.{{1,253}}$){_LABEL}(\.{_LABEL})*\.?")
_DEVICE = re.compile(r"/[A-Za-z0-9_./+@-]{1,200}")


@dataclass(frozen=True)
class Endpoint:
    """A parsed connection string: kind udpin, udpout, tcp (client), tcpin (server) or serial."""

    kind: str
    host: str = ""
    port: int = 0
    device: str = ""
    baud: int = 0

    def __str__(self) -> str:
        if self.kind == "serial":
            return f"serial {self.device} at {self.baud} baud"
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"{self.kind} {host}:{self.port}"


def parse_connection(text: str) -> Endpoint:
    """The Endpoint a connection string names; raises ValueError saying what is wrong and what is
    accepted. Pure: no name resolution, no file access (a device may appear later, a name resolve later)."""
    if not isinstance(text, str) or not text or len(text) > MAX_TEXT:
        raise ValueError(f"connection string must be a non-empty string of at most {MAX_TEXT} characters")
    if not text.isprintable() or any(c.isspace() for c in text):
        raise ValueError(f"{text!r}: no spaces or control characters allowed in a connection string")
    if text.startswith("/"):
        device, comma, baud = text.partition(",")
        return _serial(text, device, baud if comma else None)
    scheme, colon, rest = text.partition(":")
    scheme = scheme.lower()
    if not colon or (scheme not in SCHEMES and scheme != "serial"):
        raise ValueError(f"{text!r} is not a MAVLink connection string; use {FORMS}")
    url = rest.startswith("//")
    if url:
        rest = rest[2:]
    if scheme == "serial":
        device, baud = rest, None
        head, colon, tail = rest.rpartition(":")
        if colon:
            device, baud = head, tail
        return _serial(text, device, baud)
    kind = SCHEMES[scheme]
    host, colon, port = rest.rpartition(":")
    if not colon or not port.isdigit():
        raise ValueError(f"{text!r}: expected {scheme}:{'//' if url else ''}HOST:PORT")
    if not 1 <= int(port) <= 65535:
        raise ValueError(f"{text!r}: port {port} is outside 1..65535")
    if not host:
        if kind not in LISTENING:
            raise ValueError(f"{text!r}: {scheme} needs the address to send to")
        host = "0.0.0.0"
    return Endpoint(kind, _host(text, host), int(port))


def _host(text: str, host: str) -> str:
    if host.startswith("[") and host.endswith("]"):
        try:
            return str(ipaddress.IPv6Address(host[1:-1]))
        except ValueError as e:
            raise ValueError(f"{text!r}: {host} is not an IPv6 address ({e})") from None
    if ":" in host:
        raise ValueError(f"{text!r}: write an IPv6 address in brackets, e.g. udpin:[::1]:14540")
    try:
        return str(ipaddress.IPv4Address(host))
    except ValueError:
        pass
    if re.fullmatch(r"[0-9.]+", host) or not _HOSTNAME.fullmatch(host):
        raise ValueError(f"{text!r}: {host!r} is neither an IP address nor a host name")
    return host


def _serial(text: str, device: str, baud: str | None) -> Endpoint:
    if not _DEVICE.fullmatch(device) or "/../" in device + "/":
        raise ValueError(f"{text!r}: a serial port is an absolute device path such as /dev/ttyACM0")
    if baud is None:
        rate = DEFAULT_BAUD
    elif baud.isdigit() and BAUD_RANGE[0] <= int(baud) <= BAUD_RANGE[1]:
        rate = int(baud)
    else:
        raise ValueError(
            f"{text!r}: baud rate {baud!r} is not a number in {BAUD_RANGE[0]}..{BAUD_RANGE[1]} "
            "(e.g. /dev/ttyACM0,921600)"
        )
    return Endpoint("serial", device=device, baud=rate)

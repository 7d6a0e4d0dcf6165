"""Finding peers: expand the configured addresses (lists, ranges, host:port) into targets and
probe them all at once with non-blocking connects and a short timeout (thesis §7.3)."""

import errno
import ipaddress
import logging
import selectors
import socket
import time

from coopd.net import family_of, resolve

log = logging.getLogger("coopd.sharing")

MAX_TARGETS = 4096
"""A range larger than this is a configuration error, not a scan."""


def parse_targets(specs, ports) -> list[tuple[str, int]]:
    """(host, port) pairs for specs like '10.42.0.1-10.42.0.20', '10.42.0.7', 'host:7401',
    '10.42.0.1-20' (last octet range), 'fd00::7' or '[fd00::7]:7401' (IPv6) combined with every port in
    `ports` unless a spec has its own; ValueError naming the spec otherwise. `coopd --check-config`
    checks sharing.peers with this same function."""
    ports = [int(p) for p in ports]
    out: list[tuple[str, int]] = []
    for spec in specs:
        spec = spec.strip()
        if not spec:
            continue
        host, port = split_spec(spec)
        spec_ports = ports if port is None else [port]
        for addr in _expand_hosts(host):
            out.extend((addr, p) for p in spec_ports)
        if len(out) > MAX_TARGETS:
            raise ValueError(f"peer address list expands to more than {MAX_TARGETS} targets")
    for _, p in out:
        if not 0 < p < 65536:
            raise ValueError(f"port {p} out of range")
    return list(dict.fromkeys(out))


def split_spec(spec: str) -> tuple[str, int | None]:
    """'HOST' / 'HOST:PORT' / IPv6 'ADDR' / '[ADDR]' / '[ADDR]:PORT' -> (host, port or None)."""
    host, port = spec, None
    if spec.startswith("["):
        host, bracket, rest = spec[1:].partition("]")
        if not bracket or (rest and not rest.startswith(":")):
            raise ValueError(f"peer {spec!r}: write an IPv6 peer as [ADDRESS] or [ADDRESS]:PORT")
        port = rest[1:] if rest else None
        host = _ipv6(spec, host)
    elif spec.count(":") == 1:
        host, port = spec.rsplit(":", 1)
    elif ":" in spec:
        host = _ipv6(spec, spec)
    if not host or any(c.isspace() for c in host):
        raise ValueError(f"peer {spec!r} has no usable host")
    if port is not None and not (port.isdigit() and 1 <= int(port) <= 65535):
        raise ValueError(f"port of peer {spec!r} is outside 1..65535")
    return host, None if port is None else int(port)


def _ipv6(spec: str, text: str) -> str:
    try:
        return str(ipaddress.IPv6Address(text))
    except ValueError as e:
        raise ValueError(f"peer {spec!r}: {e}") from None


def _expand_hosts(host: str) -> list[str]:
    if "-" not in host or ":" in host:
        return [host]
    lo, hi = (part.strip() for part in host.split("-", 1))
    try:
        first = ipaddress.IPv4Address(lo)
        if "." not in hi:
            hi = ".".join(lo.split(".")[:3] + [hi])
        last = ipaddress.IPv4Address(hi)
    except ValueError as e:
        raise ValueError(f"peer range {host!r}: {e}") from None
    if int(last) < int(first):
        raise ValueError(f"address range {host} runs backwards")
    if int(last) - int(first) >= MAX_TARGETS:
        raise ValueError(f"address range {host} holds more than {MAX_TARGETS} addresses")
    return [str(ipaddress.IPv4Address(i)) for i in range(int(first), int(last) + 1)]


def peer_address(host: str) -> str:
    """A connection's remote address as peers are known by: an IPv4 peer reaching a dual-stack
    listener ('::') shows as '::ffff:a.b.c.d', which is the IPv4 peer a.b.c.d."""
    if host.startswith("::ffff:"):
        try:
            mapped = ipaddress.IPv6Address(host).ipv4_mapped
        except ValueError:
            return host
        if mapped is not None:
            return str(mapped)
    return host


PROBE_BATCH = 256
"""Targets probed at once: bounds the file descriptors a scan holds."""


def probe(targets, timeout: float, source: str | None = None) -> list[tuple[tuple[str, int], socket.socket]]:
    """Connect to all targets (PROBE_BATCH at a time) from `source` (an address of ours, or any; used
    for targets of its address family); return the connected sockets (blocking mode)."""
    targets = list(targets)
    connected = []
    for i in range(0, len(targets), PROBE_BATCH):
        connected += _probe_batch(targets[i:i + PROBE_BATCH], timeout, source)
    return connected


def _probe_batch(targets, timeout: float, source: str | None) -> list[tuple[tuple[str, int], socket.socket]]:
    sel = selectors.DefaultSelector()
    pending: dict[socket.socket, tuple[str, int]] = {}
    connected = []
    try:
        for target in targets:
            try:
                family, address = resolve(*target, socket.SOCK_STREAM)  # a name: IPv4 or IPv6
            except OSError:  # an unresolvable name
                continue
            try:
                s = socket.socket(family, socket.SOCK_STREAM)
            except OSError as e:  # out of file descriptors: probe the rest next scan
                log.warning("discovery: cannot open a socket (%s); %d targets left for the next scan",
                            e, len(targets) - len(pending))
                break
            s.setblocking(False)
            try:
                if source and family_of(source) == family:  # a source of the other family cannot bind
                    s.bind((source, 0))
                rc = s.connect_ex(address)
            except OSError:
                s.close()
                continue
            if rc not in (0, errno.EINPROGRESS, errno.EWOULDBLOCK):
                s.close()
                continue
            pending[s] = target
            sel.register(s, selectors.EVENT_WRITE)
        deadline = time.monotonic() + timeout
        while pending:
            left = deadline - time.monotonic()
            if left <= 0:
                break
            for key, _ in sel.select(left):
                s = key.fileobj
                sel.unregister(s)
                target = pending.pop(s)
                if s.getsockopt(socket.SOL_SOCKET, socket.SO_ERROR) == 0:
                    s.setblocking(True)
                    connected.append((target, s))
                else:
                    s.close()
    finally:
        for s in pending:
            s.close()
        sel.close()
    return connected

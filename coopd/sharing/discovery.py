"""Finding peers: expand the configured addresses (lists, ranges, host:port) into targets and
probe them all at once with non-blocking connects and a short timeout (thesis §7.3)."""

import errno
import ipaddress
import logging
import selectors
import socket
import time

log = logging.getLogger("coopd.sharing")

MAX_TARGETS = 4096
"""A range larger than this is a configuration error, not a scan."""


def parse_targets(specs, ports) -> list[tuple[str, int]]:
    """(host, port) pairs for specs like '10.42.0.1-10.42.0.20', '10.42.0.7', 'host:7401',
    '10.42.0.1-20' (last octet range) combined with every port in `ports` unless a spec has its own."""
    ports = [int(p) for p in ports]
    out: list[tuple[str, int]] = []
    for spec in specs:
        spec = spec.strip()
        if not spec:
            continue
        host, spec_ports = spec, ports
        if spec.count(":") == 1:
            host, port = spec.rsplit(":", 1)
            spec_ports = [int(port)]
        for addr in _expand_hosts(host):
            out.extend((addr, p) for p in spec_ports)
        if len(out) > MAX_TARGETS:
            raise ValueError(f"peer address list expands to more than {MAX_TARGETS} targets")
    for _, p in out:
        if not 0 < p < 65536:
            raise ValueError(f"port {p} out of range")
    return list(dict.fromkeys(out))


def _expand_hosts(host: str) -> list[str]:
    if "-" not in host:
        return [host]
    lo, hi = (part.strip() for part in host.split("-", 1))
    first = ipaddress.IPv4Address(lo)
    if "." not in hi:
        hi = ".".join(lo.split(".")[:3] + [hi])
    last = ipaddress.IPv4Address(hi)
    if int(last) < int(first):
        raise ValueError(f"address range {host} runs backwards")
    if int(last) - int(first) >= MAX_TARGETS:
        raise ValueError(f"address range {host} holds more than {MAX_TARGETS} addresses")
    return [str(ipaddress.IPv4Address(i)) for i in range(int(first), int(last) + 1)]


PROBE_BATCH = 256
"""Targets probed at once: bounds the file descriptors a scan holds."""


def probe(targets, timeout: float, source: str | None = None) -> list[tuple[tuple[str, int], socket.socket]]:
    """Connect to all targets (PROBE_BATCH at a time) from `source` (an address of ours, or any);
    return the connected sockets (blocking mode)."""
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
                s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            except OSError as e:  # out of file descriptors: probe the rest next scan
                log.warning("discovery: cannot open a socket (%s); %d targets left for the next scan",
                            e, len(targets) - len(pending))
                break
            s.setblocking(False)
            try:
                if source:
                    s.bind((source, 0))
                rc = s.connect_ex(target)
            except OSError:  # e.g. an unresolvable name
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

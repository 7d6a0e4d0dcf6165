"""Loopback facts shared by network tests."""

import socket


def has_ipv6_loopback() -> bool:
    """True when ::1 can be bound here (containers without IPv6 cannot): IPv6 tests skip otherwise."""
    try:
        with socket.socket(socket.AF_INET6, socket.SOCK_STREAM) as s:
            s.bind(("::1", 0))
        return True
    except OSError:
        return False

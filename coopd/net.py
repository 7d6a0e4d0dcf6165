"""Address helpers shared by the FC link and map sharing: IPv4 and IPv6 alike."""

import socket


def resolve(host: str, port: int, socktype: int, passive: bool = False) -> tuple[int, tuple]:
    """(address family, socket address) of host:port, IPv4 or IPv6, the resolver's first answer;
    OSError when the name does not resolve (a name may block in the resolver, a literal never)."""
    flags = socket.AI_PASSIVE if passive else 0
    infos = socket.getaddrinfo(host, port, socket.AF_UNSPEC, socktype, 0, flags | socket.AI_NUMERICSERV)
    if not infos:
        raise OSError(f"{host}: no address")
    family, _, _, _, address = infos[0]
    return family, address


def family_of(host: str) -> int:
    """AF_INET6 for an IPv6 literal, else AF_INET (IPv4 literals and host names)."""
    return socket.AF_INET6 if ":" in host else socket.AF_INET


def host_port(host: str, port: int) -> str:
    """'host:port', an IPv6 host in brackets ('[fd00::7]:7400'), as coopd.toml writes them."""
    return f"[{host}]:{port}" if ":" in host else f"{host}:{port}"


def listening_socket(family: int, kind: int) -> socket.socket:
    """A socket to bind a listening address to (SO_REUSEADDR); IPv6 ones dual-stack, so '::' takes
    IPv4 peers too whatever net.ipv6.bindv6only says."""
    s = socket.socket(family, kind)
    try:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        if family == socket.AF_INET6:
            s.setsockopt(socket.IPPROTO_IPV6, socket.IPV6_V6ONLY, 0)
    except OSError:
        s.close()
        raise
    return s

"""firmware_sim.netns: a drone's wired FC cable and its radio are separate (either can be cut
alone), and every cable is removed by cleanup() and, after a kill -9, by remove_stale()."""

import os
import socket
import subprocess
import sys

import pytest

from firmware_sim.netns import FC_LINK_PREFIX, NetnsLab, netns_unavailable_reason, remove_stale
from tests.proof import skip_proof

REASON = netns_unavailable_reason()


@pytest.fixture(autouse=True)
def _needs_netns():
    if REASON is not None:
        skip_proof(f"needs network namespaces: {REASON}")
SEND = ("import socket, sys; "
        "socket.socket(socket.AF_INET, socket.SOCK_DGRAM).sendto(b'x', (sys.argv[1], 22990))")


def root_links() -> str:
    return subprocess.run(["ip", "-o", "link", "show"], capture_output=True, text=True, timeout=10).stdout


def arrives(lab: NetnsLab, host: int, listener: socket.socket) -> bool:
    """Whether a datagram sent from inside host to the listener's address arrives within 1 s."""
    addr = listener.getsockname()[0]
    subprocess.run(lab.command(host, [sys.executable, "-c", SEND, addr]), timeout=20, capture_output=True)
    listener.settimeout(1.0)
    try:
        return listener.recv(10) == b"x"
    except TimeoutError:
        return False


def test_fc_cable_and_radio_are_cut_separately():
    # .250: outside the /24s the swarm tests take in the root namespace (10.214/10.215 .2-.199), which
    # may run at the same time on another pytest-xdist worker
    lab = NetnsLab("coopdt-fc", "10.213.250", "10.215.250")
    radio = fc = None
    try:
        lab.add_host(1)
        root_radio = lab.attach_root()
        root_fc, host_fc = lab.add_fc_link(1)
        assert lab.fc_addresses(1) == (root_fc, host_fc) == ("10.215.250.5", "10.215.250.6")
        name = lab.fc_links[1]
        assert name.startswith(FC_LINK_PREFIX) and len(name) <= 15 and name in root_links()
        radio = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        radio.bind((root_radio, 22990))
        fc = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        fc.bind((root_fc, 22990))
        assert arrives(lab, 1, radio) and arrives(lab, 1, fc)
        lab.link(1, up=False)
        assert not arrives(lab, 1, radio) and arrives(lab, 1, fc)
        lab.link(1, up=True)
        lab.fc_link(1, up=False)
        assert arrives(lab, 1, radio) and not arrives(lab, 1, fc)
        lab.fc_link(1, up=True)
        assert arrives(lab, 1, fc)
    finally:
        for s in (radio, fc):
            if s is not None:
                s.close()
        lab.cleanup()
    assert name not in root_links() and lab.fc_links == {}


def test_remove_stale_removes_a_dead_process_fc_cable():
    dead = subprocess.Popen(["true"])
    dead.wait()
    assert not os.path.exists(f"/proc/{dead.pid}")
    name = f"{FC_LINK_PREFIX}{dead.pid}z9"
    subprocess.run(["ip", "link", "add", name, "type", "veth", "peer", "name", f"{name}p"],
                   check=True, timeout=10)
    try:
        assert name in remove_stale("coopdt-none")
        assert name not in root_links()
    finally:
        subprocess.run(["ip", "link", "del", name], capture_output=True, timeout=10)

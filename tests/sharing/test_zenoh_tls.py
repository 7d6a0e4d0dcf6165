"""Zenoh over TLS (coopd.sharing.zenoh_tls): the settings are checked when loaded, and on loopback two
drones whose certificates the swarm CA signed exchange a map while a host holding the swarm key but
no such certificate gets nothing. Sessions listen and connect on 127.0.0.1 only, multicast off."""

import json
import shutil
import subprocess

import pytest
import sharing_testmsg as tm
from sharing_support import settings, wait_until
from tls_certs import TestCA

from coopd.daemon.config import ConfigError, from_dict
from coopd.sharing.service import SharingConfig, SharingService
from coopd.sharing.zenoh_link import ZenohSettings, zenoh_config
from tests.docs_examples import tls_recipe
from tests.ports import zenoh_port

zenoh = pytest.importorskip("zenoh")

KEY = b"k" * 32
NO_PEER_WAIT_S = 3.0
"""How long a host without a swarm certificate is given to get the map (it must not)."""


@pytest.fixture(scope="module")
def pki(tmp_path_factory):
    """The swarm CA with drones d1 and d2, and another CA with drone x1."""
    directory = tmp_path_factory.mktemp("tls")
    swarm, other = TestCA(directory, "swarm-ca"), TestCA(directory, "other-ca")
    return {"ca": str(swarm.path), "other_ca": str(other.path), "d1": swarm.leaf("d1"),
            "d2": swarm.leaf("d2"), "x1": other.leaf("x1")}


def tls_settings(port: int, connect=(), *, ca: str, pair, protocol: str = "tls") -> ZenohSettings:
    return ZenohSettings(swarm="t", listen=(f"{protocol}/127.0.0.1:{port}",),
                         connect=tuple(f"{protocol}/127.0.0.1:{p}" for p in connect),
                         multicast_scouting=False, tls_root_ca=ca, tls_certificate=pair[0],
                         tls_private_key=pair[1])


def test_tls_settings_become_zenohs_link_configuration(pki):
    z = tls_settings(7447, ca=pki["ca"], pair=pki["d1"])
    tls = json.loads(zenoh_config(z, 1 << 20).get_json("transport/link/tls"))
    cert, key = pki["d1"]
    assert tls["root_ca_certificate"] == pki["ca"] and tls["enable_mtls"] is True
    assert tls["verify_name_on_connect"] is True
    assert (tls["listen_certificate"], tls["listen_private_key"]) == (cert, key)
    assert (tls["connect_certificate"], tls["connect_private_key"]) == (cert, key)


def test_tls_settings_are_checked_when_loaded(pki, tmp_path):
    ca, other_ca = pki["ca"], pki["other_ca"]
    (cert, key), (_, key2), (x_cert, x_key) = pki["d1"], pki["d2"], pki["x1"]
    garbage = tmp_path / "garbage.pem"
    garbage.write_text("not a certificate\n")
    tls = dict(listen=("tls/127.0.0.1:7447",), tls_root_ca=ca, tls_certificate=cert, tls_private_key=key)
    cases = [
        (dict(listen=("tls/127.0.0.1:7447",)), "needs tls_root_ca"),
        (dict(connect=("quic/10.0.0.1:7447",)), "needs tls_root_ca"),
        ({**tls, "listen": ("tcp/127.0.0.1:7447",)}, "no listen or connect endpoint is tls/ or quic/"),
        ({**tls, "connect": ("tcp/127.0.0.1:7448",)}, "every endpoint is tls/ or quic/"),
        ({**tls, "listen": ()} | {"connect": ("tls/127.0.0.1:7448",)}, "empty listens on Zenoh's default"),
        ({**tls, "tls_root_ca": ""}, "swarm CA's certificate is needed"),
        ({**tls, "tls_private_key": ""}, "set together"),
        ({**tls, "tls_certificate": "", "tls_private_key": ""}, "presents one on its TLS listen"),
        ({**tls, "tls_root_ca": str(tmp_path / "missing.pem")}, "tls_root_ca: cannot read"),
        ({**tls, "tls_root_ca": str(tmp_path)}, "tls_root_ca: cannot read"),  # a directory
        ({**tls, "tls_root_ca": "relative/ca.pem"}, "must be an absolute path"),
        ({**tls, "tls_root_ca": str(garbage)}, "holds no PEM certificate"),
        ({**tls, "tls_certificate": key}, "tls_certificate: .* holds no PEM certificate"),
        ({**tls, "tls_private_key": cert}, "holds no PEM private key"),
        ({**tls, "tls_private_key": key2}, "is not the key of the certificate"),
        ({**tls, "tls_certificate": x_cert, "tls_private_key": x_key}, "is not signed by the CA"),
        ({**tls, "tls_root_ca": other_ca}, "is not signed by the CA"),
    ]
    for bad, message in cases:
        with pytest.raises(ValueError, match=message):
            ZenohSettings(**bad)
    client = dict(mode="client", connect=("tls/127.0.0.1:7447",), tls_root_ca=ca)
    with pytest.raises(ValueError, match="tls_client_auth: mutual TLS needs"):
        ZenohSettings(**client)
    assert ZenohSettings(**client, tls_client_auth=False).tls_certificate == ""  # a client without one
    assert ZenohSettings(**tls).tls_root_ca == ca
    assert ZenohSettings(**{**tls, "listen": ("quic/127.0.0.1:7447",)}).tls_certificate == cert


def test_a_config_file_with_a_bad_tls_setting_names_the_key(pki):
    zenoh = {"listen": ["tls/127.0.0.1:7447"], "tls_root_ca": pki["ca"] + ".missing",
             "tls_certificate": pki["d1"][0], "tls_private_key": pki["d1"][1]}
    with pytest.raises(ConfigError, match="cannot read") as e:
        from_dict({"sharing": {"transport": "zenoh", "zenoh": zenoh}})
    assert e.value.key == "sharing.zenoh.tls_root_ca"
    with pytest.raises(ConfigError, match="must be a string"):
        from_dict({"sharing": {"zenoh": {"tls_root_ca": 3}}})


def node(vid: int, z: ZenohSettings) -> SharingService:
    cfg = SharingConfig(vehicle_id=vid, mtp=False, zenoh=z, transport=settings(swarm_key=KEY))
    return SharingService(cfg, inspect=tm.inspect).start()


def intruder(port: int, connect_port: int, ca: str, pair, protocol: str):
    """A plain Zenoh session that trusts the swarm CA and presents `pair` (None: no certificate)."""
    tls = {"root_ca_certificate": ca, "enable_mtls": pair is not None}
    if pair is not None:
        tls.update(listen_certificate=pair[0], listen_private_key=pair[1], connect_certificate=pair[0],
                   connect_private_key=pair[1])
    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    if pair is not None:
        conf.insert_json5("listen/endpoints", json.dumps([f"{protocol}/127.0.0.1:{port}"]))
    conf.insert_json5("connect/endpoints", json.dumps([f"{protocol}/127.0.0.1:{connect_port}"]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("transport/link/tls", json.dumps(tls))
    return zenoh.open(conf)


@pytest.mark.parametrize("protocol", ["tls", "quic"])
def test_only_drones_with_a_swarm_certificate_get_the_map(pki, protocol):
    """d1 and d2 (certificates of the swarm CA) exchange a map over TLS (or QUIC: the same settings);
    a host that trusts the swarm CA but presents another CA's certificate, and one that presents none,
    never open a link with d1: they neither receive the map nor get it by query."""
    ca = pki["ca"]
    ports = [zenoh_port() for _ in range(3)]
    a = node(1, tls_settings(ports[0], ca=ca, pair=pki["d1"], protocol=protocol))
    b = node(2, tls_settings(ports[1], [ports[0]], ca=ca, pair=pki["d2"], protocol=protocol))
    outsiders = [intruder(ports[2], ports[0], ca, pki["x1"], protocol),
                 intruder(0, ports[0], ca, None, protocol)]
    heard = []
    try:
        for o in outsiders:
            o.declare_subscriber("coopd/t/**", heard.append)
        assert wait_until(lambda: a.stats()["zenoh"]["peers"], 10), a.stats()["zenoh"]
        a.publish(tm.make(1, 5, b"for the swarm"), 5)
        assert wait_until(lambda: b.received.version(1) == 5, 10), b.stats()["zenoh"]
        assert tm.payload(b.received.get(1).data) == b"for the swarm"
        assert not wait_until(lambda: heard, NO_PEER_WAIT_S)
        for o in outsiders:
            assert [r for r in o.get("coopd/t/1/*", timeout=1.0) if r.ok is not None] == []
            assert list(o.info.peers_zid()) == []
        assert a.stats()["zenoh"]["peers"] == [b.stats()["zenoh"]["zid"]]
    finally:
        for o in outsiders:
            o.close()
        b.stop()
        a.stop()


@pytest.mark.skipif(shutil.which("openssl") is None, reason="needs the openssl command")
def test_the_openssl_recipe_in_the_docs_makes_certificates_that_work(tmp_path):
    """The commands of docs/sharing.md as printed (drone 3's address made 127.0.0.1, and run for drones
    1 and 2): coopd's checks take the files, and the two drones exchange a map over TLS."""
    make_ca, make_drone = tls_recipe()

    def sh(script: str) -> None:
        subprocess.run(["sh", "-e", "-c", script], cwd=tmp_path, check=True, capture_output=True, timeout=60)

    sh(make_ca)
    for n in (1, 2):
        sh(make_drone.replace("drone3", f"drone{n}").replace("10.42.0.3", "127.0.0.1"))
    ca = str(tmp_path / "swarm-ca.pem")
    pairs = [(str(tmp_path / f"drone{n}.pem"), str(tmp_path / f"drone{n}.key")) for n in (1, 2)]
    ports = [zenoh_port() for _ in range(2)]
    a = node(1, tls_settings(ports[0], ca=ca, pair=pairs[0]))
    b = node(2, tls_settings(ports[1], [ports[0]], ca=ca, pair=pairs[1]))
    try:
        a.publish(tm.make(1, 3, b"recipe"), 3)
        assert wait_until(lambda: b.received.version(1) == 3, 10), (a.stats()["zenoh"], b.stats()["zenoh"])
    finally:
        b.stop()
        a.stop()

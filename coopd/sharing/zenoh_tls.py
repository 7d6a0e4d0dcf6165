"""TLS links for Zenoh ([sharing.zenoh] tls_*, docs/sharing.md "Zenoh"): the checks the settings pass
when they are loaded, and the Zenoh configuration they become (transport/link/tls of eclipse-zenoh 1.x,
which serves tls/ and quic/ endpoints alike).

With a swarm CA, every drone presents a certificate the CA signed and, with client authentication
(mutual TLS, the default), accepts a link only from a peer whose certificate the CA signed: a host
without such a certificate cannot open a Zenoh session with any drone. The swarm key still
authenticates every message on top (zenoh_link's envelope)."""

from __future__ import annotations

TLS_PROTOCOLS = ("tls", "quic")
MAX_PEM_BYTES = 1 << 20
"""A certificate chain or key file larger than this is refused (no unbounded read of a config file)."""


def is_tls(endpoint: str) -> bool:
    return endpoint.split("/", 1)[0] in TLS_PROTOCOLS


def check_tls(settings) -> None:
    """ValueError naming the setting when the TLS settings of a ZenohSettings do not make every link a
    TLS link checked against the swarm CA: a tls/ or quic/ endpoint without them, them without such an
    endpoint, a plain endpoint next to them, or files that are missing, unreadable, not PEM, a key that
    is not the certificate's, a certificate the CA did not sign."""
    s = settings
    endpoints = (*s.listen, *s.connect)
    secured = [e for e in endpoints if is_tls(e)]
    if not (s.tls_root_ca or s.tls_certificate or s.tls_private_key):
        if secured:
            raise ValueError(f"endpoint {secured[0]!r} needs tls_root_ca (the swarm CA: without it Zenoh "
                             "would trust any certificate a public CA signed)")
        return
    if not secured:
        raise ValueError("the tls_* settings are set but no listen or connect endpoint is tls/ or quic/: "
                         "the links would not use them")
    plain = [e for e in endpoints if not is_tls(e)]
    if plain:
        raise ValueError(f"endpoint {plain[0]!r}: with the tls_* settings every endpoint is tls/ or quic/ "
                         "(a plain link would let any host in)")
    if s.mode != "client" and not s.listen:
        raise ValueError("listen: with the tls_* settings a peer or router lists its tls/ or quic/ endpoints "
                         "(empty listens on Zenoh's default, plain TCP)")
    if not s.tls_root_ca:
        raise ValueError("tls_root_ca: the swarm CA's certificate is needed (without it Zenoh would trust "
                         "any certificate a public CA signed)")
    if bool(s.tls_certificate) != bool(s.tls_private_key):
        raise ValueError("tls_certificate and tls_private_key are set together")
    if not s.tls_certificate and s.mode != "client":
        raise ValueError("tls_certificate: a peer or router presents one on its TLS listen endpoints")
    if not s.tls_certificate and s.tls_client_auth:
        raise ValueError("tls_client_auth: mutual TLS needs tls_certificate and tls_private_key (or set "
                         "tls_client_auth = false for a client that presents none)")
    roots = _certificates("tls_root_ca", s.tls_root_ca)
    if s.tls_certificate:
        chain = _certificates("tls_certificate", s.tls_certificate)
        key = _private_key("tls_private_key", s.tls_private_key)
        _check_pair(chain, key, s.tls_certificate)
        if not any(_issued(chain[0], issuer) for issuer in (*roots, *chain[1:])):
            raise ValueError(f"tls_certificate: {s.tls_certificate} is not signed by the CA in "
                             f"{s.tls_root_ca} (peers would refuse it)")


def tls_config(settings) -> dict | None:
    """The transport/link/tls table of a Zenoh configuration for these settings; None without TLS."""
    s = settings
    if not s.tls_root_ca:
        return None
    table = {"root_ca_certificate": s.tls_root_ca, "enable_mtls": s.tls_client_auth,
             "verify_name_on_connect": s.tls_verify_name}
    if s.tls_certificate:
        table.update(listen_certificate=s.tls_certificate, listen_private_key=s.tls_private_key,
                     connect_certificate=s.tls_certificate, connect_private_key=s.tls_private_key)
    return table


def describe_tls(settings) -> str:
    """One phrase for the startup log line."""
    s = settings
    if not s.tls_root_ca:
        return "links without TLS"
    auth = "mutual TLS" if s.tls_client_auth else "TLS, peers' certificates not required"
    return f"{auth} under the CA in {s.tls_root_ca}"


def _read(name: str, path: str) -> bytes:
    if not path.startswith("/") or "\0" in path:
        raise ValueError(f"{name}: {path!r} must be an absolute path")
    try:
        with open(path, "rb") as f:
            data = f.read(MAX_PEM_BYTES + 1)
    except OSError as e:
        raise ValueError(f"{name}: cannot read {path} ({e.strerror or e})") from None
    if len(data) > MAX_PEM_BYTES:
        raise ValueError(f"{name}: {path} is larger than {MAX_PEM_BYTES} bytes")
    return data


def _certificates(name: str, path: str) -> list:
    from cryptography import x509

    try:
        return x509.load_pem_x509_certificates(_read(name, path))
    except ValueError as e:
        if str(e).startswith(name):
            raise
        raise ValueError(f"{name}: {path} holds no PEM certificate ({e})") from None


def _private_key(name: str, path: str):
    from cryptography.exceptions import UnsupportedAlgorithm
    from cryptography.hazmat.primitives import serialization

    data = _read(name, path)
    try:
        return serialization.load_pem_private_key(data, password=None)
    except TypeError:  # encrypted
        raise ValueError(f"{name}: {path} is encrypted; Zenoh reads unencrypted PEM keys only") from None
    except (ValueError, UnsupportedAlgorithm) as e:
        raise ValueError(f"{name}: {path} holds no PEM private key ({e})") from None


def _check_pair(chain: list, key, cert_path: str) -> None:
    from cryptography.hazmat.primitives import serialization

    spki = serialization.Encoding.DER, serialization.PublicFormat.SubjectPublicKeyInfo
    if chain[0].public_key().public_bytes(*spki) != key.public_key().public_bytes(*spki):
        raise ValueError(f"tls_private_key is not the key of the certificate in {cert_path}")


def _issued(certificate, issuer) -> bool:
    try:
        certificate.verify_directly_issued_by(issuer)
    except Exception:  # another issuer's name (ValueError), a bad signature, a key type it cannot check
        return False
    return True

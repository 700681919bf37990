"""A small certificate authority for the fleet's mutual TLS: one CA, a server certificate for the shore
router and a client certificate for each vessel and for the operator.

The router's access control tells boats apart by the common name of the certificate they present, so the
names here are part of the security contract: `router`, `vessel-<id>` and `operator`. Keys are ECDSA P-256
(small, fast on a boat's PC, accepted by rustls) and are written readable by their owner only.

This is meant for tests and for a field deployment run by one operator; it is not a substitute for a real
PKI (no revocation, the CA key sits next to the certificates it signed).
"""

from __future__ import annotations

import datetime
import ipaddress
import os
from pathlib import Path

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from usv_deploy.security import check_name, check_vessel_id, vessel_subject

DEFAULT_HOSTS = ("localhost", "127.0.0.1")
# Certificates start a little in the past so a boat whose clock lags the laptop's still accepts them.
CLOCK_SLACK = datetime.timedelta(minutes=5)


def make_certificates(out: Path, vessels: list[str], operator: str = "operator", router: str = "router",
                      hosts: list[str] | None = None, days: int = 365) -> dict[str, dict[str, Path]]:
    """Create the CA and the router's, each vessel's and the operator's key and certificate in `out`.

    Returns the paths by name: {"ca": {"cert", "key"}, router: {...}, "vessel-<id>": {...}, operator: {...}}.
    Files are `<name>.pem` and `<name>-key.pem`. Raises ValueError on a bad vessel id, a bad name or a clash
    between names, before anything is written.
    """
    names = _client_names(vessels, operator, router)
    if days < 1:
        raise ValueError(f"days must be at least 1, not {days}")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    now = datetime.datetime.now(datetime.timezone.utc)
    validity = (now - CLOCK_SLACK, now + datetime.timedelta(days=days))

    ca_key = _new_key()
    ca_cert = _ca_certificate(ca_key, validity)
    paths = {"ca": _write_pair(out, "ca", ca_cert, ca_key)}
    server_key = _new_key()
    server_cert = _leaf_certificate(router, server_key, ca_cert, ca_key, validity,
                                    ExtendedKeyUsageOID.SERVER_AUTH, _host_names(hosts))
    paths[router] = _write_pair(out, router, server_cert, server_key)
    for name in names:
        key = _new_key()
        cert = _leaf_certificate(name, key, ca_cert, ca_key, validity, ExtendedKeyUsageOID.CLIENT_AUTH)
        paths[name] = _write_pair(out, name, cert, key)
    return paths


def _client_names(vessels: list[str], operator: str, router: str) -> list[str]:
    """The client certificates' common names, checked: each vessel once, no name used twice, no path tricks."""
    for vessel in vessels:
        check_vessel_id(vessel)
    if len(set(vessels)) != len(vessels):
        raise ValueError(f"vessel ids must be unique: {vessels}")
    check_name(operator, "operator")
    check_name(router, "router")
    names = [vessel_subject(v) for v in vessels] + [operator]
    taken = set()
    for name in names + [router, "ca"]:
        if name in taken:
            raise ValueError(f"certificate name {name!r} is used twice (operator, router and vessel-<id> must differ)")
        taken.add(name)
    return names


def _host_names(hosts: list[str] | None) -> list[x509.GeneralName]:
    """The router's subjectAltNames: IP addresses as IP SANs, anything else as DNS names; duplicates dropped."""
    names: list[x509.GeneralName] = []
    for host in dict.fromkeys([*DEFAULT_HOSTS, *(hosts or [])]):
        try:
            names.append(x509.IPAddress(ipaddress.ip_address(host)))
        except ValueError:
            if not host or any(c.isspace() or c in "/\\" for c in host):
                raise ValueError(f"bad host name for the router's certificate: {host!r}") from None
            names.append(x509.DNSName(host))
    return names


def _new_key() -> ec.EllipticCurvePrivateKey:
    return ec.generate_private_key(ec.SECP256R1())


def _name(common_name: str) -> x509.Name:
    return x509.Name([x509.NameAttribute(NameOID.ORGANIZATION_NAME, "usv-circumnav"),
                      x509.NameAttribute(NameOID.COMMON_NAME, common_name)])


def _ca_certificate(key: ec.EllipticCurvePrivateKey, validity) -> x509.Certificate:
    """A self-signed CA that may sign leaf certificates only (path length 0)."""
    name = _name("usv-circumnav test CA")
    public = key.public_key()
    builder = (
        x509.CertificateBuilder()
        .subject_name(name).issuer_name(name)
        .public_key(public)
        .serial_number(x509.random_serial_number())
        .not_valid_before(validity[0]).not_valid_after(validity[1])
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .add_extension(_key_usage(cert_sign=True), critical=True)
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(public), critical=False)
    )
    return builder.sign(key, hashes.SHA256())


def _leaf_certificate(common_name: str, key, ca_cert: x509.Certificate, ca_key, validity, usage,
                      alt_names: list[x509.GeneralName] | None = None) -> x509.Certificate:
    """An end-entity certificate for `common_name`, signed by the CA, usable for one TLS role (`usage`)."""
    public = key.public_key()
    ca_ski = ca_cert.extensions.get_extension_for_class(x509.SubjectKeyIdentifier).value
    builder = (
        x509.CertificateBuilder()
        .subject_name(_name(common_name)).issuer_name(ca_cert.subject)
        .public_key(public)
        .serial_number(x509.random_serial_number())
        .not_valid_before(validity[0]).not_valid_after(validity[1])
        .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
        .add_extension(_key_usage(cert_sign=False), critical=True)
        .add_extension(x509.ExtendedKeyUsage([usage]), critical=False)
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(public), critical=False)
        .add_extension(x509.AuthorityKeyIdentifier.from_issuer_subject_key_identifier(ca_ski), critical=False)
    )
    if alt_names:
        builder = builder.add_extension(x509.SubjectAlternativeName(alt_names), critical=False)
    return builder.sign(ca_key, hashes.SHA256())


def _key_usage(cert_sign: bool) -> x509.KeyUsage:
    """A CA signs certificates; an ECDSA leaf only signs the TLS handshake (no key encipherment with EC)."""
    return x509.KeyUsage(digital_signature=not cert_sign, content_commitment=False, key_encipherment=False,
                         data_encipherment=False, key_agreement=False, key_cert_sign=cert_sign,
                         crl_sign=cert_sign, encipher_only=False, decipher_only=False)


def _write_pair(out: Path, name: str, cert: x509.Certificate, key) -> dict[str, Path]:
    """Write `<name>.pem` (world-readable: certificates are public) and `<name>-key.pem` (owner only)."""
    cert_path = out / f"{name}.pem"
    key_path = out / f"{name}-key.pem"
    _write(cert_path, cert.public_bytes(serialization.Encoding.PEM), 0o644)
    key_bytes = key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                                  serialization.NoEncryption())
    _write(key_path, key_bytes, 0o600)
    return {"cert": cert_path, "key": key_path}


def _write(path: Path, data: bytes, mode: int) -> None:
    """Write with `mode` from the first byte on (a key must never be readable by others, even briefly);
    fchmod covers a file that already existed with a looser mode."""
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, mode)
    with os.fdopen(fd, "wb") as file:
        os.fchmod(fd, mode)
        file.write(data)

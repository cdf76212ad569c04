"""`mrrig certs init | issue NAME --role ROLE`: a lab certificate authority for Zenoh mTLS.

`init` makes a CA (`ca.pem`, `ca-key.pem`) in the certificate folder; `issue` makes a key and a
certificate signed by it (`NAME.pem`, `NAME-key.pem`) whose common name is NAME: Zenoh's access
control matches its subjects by that name (`cert_common_names` in configs/zenoh/*.json5). The
role (observer, operator, rig, router) goes into the certificate's organisational unit, so that
`openssl x509 -subject` shows what it was issued for; the permission itself is the access
control's list of names per role.

This CA is fine for a lab's closed network. A lab with its own CA issues the certificates there
instead (same common names, the rig's with a subjectAltName for its address) and points
`root_ca_certificate` at that CA's certificate.
"""

from __future__ import annotations

import argparse
import datetime as dt
import ipaddress
import logging
import os
import re
from pathlib import Path

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from mrrig.errors import MrrigError

log = logging.getLogger(__name__)

ROLES = ("observer", "operator", "rig", "router")
DEFAULT_DIR = Path("certs")
CA_CERT, CA_KEY = "ca.pem", "ca-key.pem"
_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,62}$")
# every certificate serves 127.0.0.1 and localhost: a listener's name is checked on connect
_LOOPBACK_NAMES = ("127.0.0.1", "localhost")


class CertError(MrrigError, ValueError):
    """A certificate request that cannot be carried out; the message is one line."""


def _key() -> ec.EllipticCurvePrivateKey:
    return ec.generate_private_key(ec.SECP256R1())


def _write_key(path: Path, key: ec.EllipticCurvePrivateKey) -> None:
    data = key.private_bytes(
        serialization.Encoding.PEM,
        serialization.PrivateFormat.PKCS8,
        serialization.NoEncryption(),
    )
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "wb") as f:
        f.write(data)


def _write_cert(path: Path, cert: x509.Certificate) -> None:
    path.write_bytes(cert.public_bytes(serialization.Encoding.PEM))


def _alt_names(hosts: list[str]) -> list[x509.GeneralName]:
    names: list[x509.GeneralName] = []
    for host in dict.fromkeys([*_LOOPBACK_NAMES, *hosts]):
        try:
            names.append(x509.IPAddress(ipaddress.ip_address(host)))
        except ValueError:
            names.append(x509.DNSName(host))
    return names


def init_ca(directory: Path, days: int = 3650, force: bool = False) -> Path:
    """A new CA in `directory`; refuses to replace one unless `force`. Returns the CA cert."""
    directory.mkdir(parents=True, exist_ok=True)
    cert_path = directory / CA_CERT
    if cert_path.exists() and not force:
        raise CertError(f"{cert_path} exists (a new CA invalidates every certificate: --force)")
    key = _key()
    name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "mrrig lab CA")])
    now = dt.datetime.now(dt.UTC)
    cert = (
        x509.CertificateBuilder()
        .subject_name(name)
        .issuer_name(name)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - dt.timedelta(minutes=5))
        .not_valid_after(now + dt.timedelta(days=days))
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .add_extension(
            x509.KeyUsage(
                digital_signature=False,
                content_commitment=False,
                key_encipherment=False,
                data_encipherment=False,
                key_agreement=False,
                key_cert_sign=True,
                crl_sign=True,
                encipher_only=False,
                decipher_only=False,
            ),
            critical=True,
        )
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), False)
        .sign(key, hashes.SHA256())
    )
    _write_key(directory / CA_KEY, key)
    _write_cert(cert_path, cert)
    return cert_path


def _load_ca(directory: Path) -> tuple[x509.Certificate, ec.EllipticCurvePrivateKey]:
    cert_path, key_path = directory / CA_CERT, directory / CA_KEY
    if not cert_path.is_file() or not key_path.is_file():
        raise CertError(f"{directory}: no CA ({CA_CERT}, {CA_KEY}): run `mrrig certs init` first")
    cert = x509.load_pem_x509_certificate(cert_path.read_bytes())
    key = serialization.load_pem_private_key(key_path.read_bytes(), password=None)
    return cert, key  # type: ignore[return-value]


def issue(
    directory: Path, name: str, role: str, hosts: list[str] | None = None, days: int = 825
) -> tuple[Path, Path]:
    """A key and a certificate with common name `name` for `role`, signed by the CA in
    `directory`; valid as TLS server and client, for 127.0.0.1, localhost and `hosts`.
    Returns (certificate, key)."""
    if role not in ROLES:
        raise CertError(f"--role: unknown role {role!r} (known: {', '.join(ROLES)})")
    if not _NAME.match(name):
        raise CertError(f"NAME: {name!r} must be letters, digits, '_', '.', '-' (up to 63)")
    ca_cert, ca_key = _load_ca(directory)
    key = _key()
    now = dt.datetime.now(dt.UTC)
    cert = (
        x509.CertificateBuilder()
        .subject_name(
            x509.Name(
                [
                    x509.NameAttribute(NameOID.COMMON_NAME, name),
                    x509.NameAttribute(NameOID.ORGANIZATIONAL_UNIT_NAME, role),
                ]
            )
        )
        .issuer_name(ca_cert.subject)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - dt.timedelta(minutes=5))
        .not_valid_after(now + dt.timedelta(days=days))
        .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
        .add_extension(x509.SubjectAlternativeName(_alt_names(hosts or [])), critical=False)
        .add_extension(
            x509.ExtendedKeyUsage(
                [ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH]
            ),
            critical=False,
        )
        .sign(ca_key, hashes.SHA256())
    )
    cert_path, key_path = directory / f"{name}.pem", directory / f"{name}-key.pem"
    _write_key(key_path, key)
    _write_cert(cert_path, cert)
    return cert_path, key_path


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="mrrig certs", description=__doc__.splitlines()[0])
    ap.add_argument("--dir", type=Path, default=DEFAULT_DIR, help="certificate folder")
    sub = ap.add_subparsers(dest="action", required=True)
    init = sub.add_parser("init", help="make the lab CA (ca.pem, ca-key.pem)")
    init.add_argument("--force", action="store_true", help="replace an existing CA")
    one = sub.add_parser("issue", help="make NAME.pem and NAME-key.pem signed by the CA")
    one.add_argument("name", help="the certificate's common name (the access control's subject)")
    one.add_argument("--role", required=True, choices=ROLES)
    one.add_argument(
        "--host",
        action="append",
        default=[],
        help="an address or host name it serves besides 127.0.0.1 (repeat for several)",
    )
    args = ap.parse_args(argv)
    if args.action == "init":
        path = init_ca(args.dir, force=args.force)
        print(f"CA: {path} (key {args.dir / CA_KEY}: keep it off the rig PCs)")
        return 0
    cert, key = issue(args.dir, args.name, args.role, args.host)
    print(f"{args.role} {args.name}: {cert}, {key}")
    if args.name not in ROLES:
        print(
            f"the access control grants by common name: add {args.name!r} to the "
            f"{args.role!r} subject's cert_common_names in the rig's and the router's config"
        )
    return 0

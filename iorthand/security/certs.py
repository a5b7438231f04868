"""A small private PKI for one deployment: a CA and one certificate per role.

Roles and their certificate common names (the router's ACL matches on them, see :mod:`iorthand.security.acl`):

``router`` · ``edge-<robot>`` · ``operator-<name>`` · ``twin`` · ``recorder`` · ``replay`` · ``web`` · ``bridge`` ·
``viewer-<name>``

Keys are ECDSA P-256 (small, fast handshakes on a Pi, supported by rustls), written PKCS#8 with mode 0600 in
a 0700 directory; certificates are 0644. The CA lives 10 years, role certificates 1 year by default (short
enough that a lost laptop's certificate dies on its own, long enough not to break a clinic between visits).
Every leaf carries a subjectAltName (rustls refuses certificates without one), the router's with the host names
and addresses clients will dial; only the router's certificate is valid for serverAuth.
"""

from __future__ import annotations

import datetime as dt
import ipaddress
import os
import re
from dataclasses import dataclass
from pathlib import Path

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

CA_DAYS = 3650
LEAF_DAYS = 365
# ``bridge``: `iorthand bridge mqtt` (the ACL lets it write only the rows of the channel table naming Role.BRIDGE).
ROLE_PATTERN = re.compile(r"^(router|twin|recorder|replay|web|bridge|(edge|operator|viewer)-[A-Za-z0-9_.@-]{1,64})$")
ORGANIZATION = "iorthand"


class CertError(ValueError):
    pass


@dataclass(frozen=True)
class Issued:
    name: str
    certificate: Path
    private_key: Path


def _utcnow() -> dt.datetime:
    return dt.datetime.now(dt.UTC)


def _write(path: Path, data: bytes, mode: int) -> None:
    """Write with the final mode from the start (no window where a key is world-readable)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, mode)
    try:
        os.write(fd, data)
    finally:
        os.close(fd)
    os.chmod(tmp, mode)
    os.replace(tmp, path)


def _key_pem(key: ec.EllipticCurvePrivateKey) -> bytes:
    return key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption())


def ca_paths(directory: Path) -> tuple[Path, Path]:
    return directory / "ca.pem", directory / "ca.key"


def init_ca(directory: Path, name: str = "iorthand CA", days: int = CA_DAYS, force: bool = False) -> tuple[Path, Path]:
    """Create the CA in ``directory`` (``ca.pem``, ``ca.key``). Refuses to overwrite an existing CA unless
    ``force``: replacing it silently would orphan every issued certificate."""
    directory = Path(directory)
    cert_path, key_path = ca_paths(directory)
    if cert_path.exists() and not force:
        raise CertError(f"{cert_path} already exists (use --force to replace the CA and re-issue everything)")
    directory.mkdir(parents=True, exist_ok=True)
    os.chmod(directory, 0o700)
    key = ec.generate_private_key(ec.SECP256R1())
    subject = x509.Name([x509.NameAttribute(NameOID.ORGANIZATION_NAME, ORGANIZATION), x509.NameAttribute(NameOID.COMMON_NAME, name)])
    now = _utcnow()
    cert = (
        x509.CertificateBuilder()
        .subject_name(subject)
        .issuer_name(subject)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - dt.timedelta(minutes=5))
        .not_valid_after(now + dt.timedelta(days=days))
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .add_extension(
            x509.KeyUsage(digital_signature=True, key_cert_sign=True, crl_sign=True, content_commitment=False,
                          key_encipherment=False, data_encipherment=False, key_agreement=False,
                          encipher_only=False, decipher_only=False),
            critical=True,
        )
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
        .sign(key, hashes.SHA256())
    )
    _write(key_path, _key_pem(key), 0o600)
    _write(cert_path, cert.public_bytes(serialization.Encoding.PEM), 0o644)
    return cert_path, key_path


def _san(hosts: list[str]) -> list[x509.GeneralName]:
    out: list[x509.GeneralName] = []
    for h in hosts:
        try:
            out.append(x509.IPAddress(ipaddress.ip_address(h)))
        except ValueError:
            out.append(x509.DNSName(h))
    return out


def check_name(name: str) -> None:
    """A certificate's name, which is also its router user name: one of the roles, or CertError."""
    if not ROLE_PATTERN.match(name):
        raise CertError(
            f"certificate name {name!r} is not a role: expected router, twin, recorder, replay, web, bridge, edge-<robot>, "
            "operator-<name> or viewer-<name>"
        )


def issue(
    directory: Path,
    name: str,
    hosts: list[str] | None = None,
    days: int = LEAF_DAYS,
    out_dir: Path | None = None,
    not_before: dt.datetime | None = None,
) -> Issued:
    """Issue ``<name>.pem`` / ``<name>.key`` signed by the CA in ``directory``; ``name`` is the common name.

    ``hosts`` go into the subjectAltName (the router: its DNS names and IPs). Every certificate also carries
    its own name as a DNS SAN, which rustls needs even when names are not verified."""
    check_name(name)
    ca_cert, ca_key = load_ca(Path(directory))
    out = Path(out_dir) if out_dir else Path(directory)
    key = ec.generate_private_key(ec.SECP256R1())
    now = not_before or _utcnow()
    # Only the router may act as a TLS server: a stolen operator certificate then cannot impersonate the router
    # to a client that verifies names. The router also gets clientAuth for router-to-router chains.
    usages = [ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH] if name == "router" else [ExtendedKeyUsageOID.CLIENT_AUTH]
    sans = _san([name.replace("@", "."), *(hosts or [])])
    cert = (
        x509.CertificateBuilder()
        .subject_name(x509.Name([x509.NameAttribute(NameOID.ORGANIZATION_NAME, ORGANIZATION), x509.NameAttribute(NameOID.COMMON_NAME, name)]))
        .issuer_name(ca_cert.subject)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - dt.timedelta(minutes=5))
        .not_valid_after(now + dt.timedelta(days=days))
        .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
        .add_extension(
            x509.KeyUsage(digital_signature=True, key_cert_sign=False, crl_sign=False, content_commitment=False,
                          key_encipherment=False, data_encipherment=False, key_agreement=False,
                          encipher_only=False, decipher_only=False),
            critical=True,
        )
        .add_extension(x509.ExtendedKeyUsage(usages), critical=False)
        .add_extension(x509.SubjectAlternativeName(sans), critical=False)
        .add_extension(x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_cert.public_key()), critical=False)  # type: ignore[arg-type]
        .sign(ca_key, hashes.SHA256())
    )
    key_path, cert_path = out / f"{name}.key", out / f"{name}.pem"
    _write(key_path, _key_pem(key), 0o600)
    _write(cert_path, cert.public_bytes(serialization.Encoding.PEM), 0o644)
    return Issued(name, cert_path, key_path)


def load_ca(directory: Path) -> tuple[x509.Certificate, ec.EllipticCurvePrivateKey]:
    cert_path, key_path = ca_paths(Path(directory))
    if not cert_path.exists() or not key_path.exists():
        raise CertError(f"no CA in {directory} (run `iorthand certs init --dir {directory}` first)")
    cert = load_certificate(cert_path)
    key = serialization.load_pem_private_key(key_path.read_bytes(), password=None)
    if not isinstance(key, ec.EllipticCurvePrivateKey):
        raise CertError(f"{key_path}: the CA key is not an EC key")
    return cert, key


def load_certificate(path: Path) -> x509.Certificate:
    try:
        return x509.load_pem_x509_certificate(Path(path).read_bytes())
    except OSError as exc:
        raise CertError(f"{path}: cannot read ({exc.strerror or exc})") from None
    except ValueError as exc:
        raise CertError(f"{path}: not a PEM certificate ({exc})") from None


def common_name(cert: x509.Certificate) -> str:
    attrs = cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)
    return str(attrs[0].value) if attrs else ""


def subject_alt_names(cert: x509.Certificate) -> list[str]:
    """The names and addresses a certificate is valid for, as text (DNS names, IP addresses)."""
    try:
        return [str(getattr(v, "value", v)) for v in cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value]
    except x509.ExtensionNotFound:
        return []


def describe(path: Path) -> dict[str, object]:
    """What ``iorthand certs show`` prints: subject, issuer, validity, SANs, usages, fingerprint."""
    cert = load_certificate(path)
    sans = subject_alt_names(cert)
    try:
        is_ca = cert.extensions.get_extension_for_class(x509.BasicConstraints).value.ca
    except x509.ExtensionNotFound:
        is_ca = False
    now = _utcnow()
    left = cert.not_valid_after_utc - now
    return {
        "file": str(path),
        "common_name": common_name(cert),
        "issuer": cert.issuer.rfc4514_string(),
        "subject": cert.subject.rfc4514_string(),
        "ca": is_ca,
        "not_before": cert.not_valid_before_utc.isoformat(),
        "not_after": cert.not_valid_after_utc.isoformat(),
        # Whole days, counted toward zero: one that expired a day and some hours ago has -1 (timedelta.days: -2).
        "days_left": int(left.total_seconds() / 86400),
        "expired": now > cert.not_valid_after_utc,
        "subject_alt_names": sans,
        "serial": f"{cert.serial_number:x}",
        "sha256": cert.fingerprint(hashes.SHA256()).hex(":"),
    }

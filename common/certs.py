"""A site's own certificate authority and one certificate per host, for zenoh over TLS.

Every host of a home proves who it is with a certificate signed by the site's
authority; the router's access control knows each host by its certificate's
common name (:func:`common_name`). Files written into one folder::

    ca.pem, ca-key.pem                the authority (keep ca-key.pem off the network)
    <name>.pem, <name>-key.pem        one host: router, fusion, each camera id, each reader

Private keys are written with mode 0600. Every certificate names ``localhost``
and ``127.0.0.1`` among its subject alternative names, plus the host names it
is given: a TLS client checks the name in the endpoint it connects to
(``tls/fusion.local:7447``) against the certificate of the host it reaches.
"""

from __future__ import annotations

import datetime as _dt
import ipaddress
import os
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

from common import keys

CA_FILE = "ca.pem"
CA_KEY_FILE = "ca-key.pem"
ROUTER = "router"
FUSION = "fusion"
DEFAULT_READERS = ("reader",)
DEFAULT_DAYS = 3650
LOCAL_NAMES = ("localhost", "127.0.0.1")


class CertError(ValueError):
    """Certificates that cannot be made as asked; the message says why."""


def common_name(role: str, name: str = "") -> str:
    """The certificate common name a host is known by in the access control.

    ``common_name("router")``, ``common_name("fusion")``, ``common_name("camera", "cam1")``
    -> ``camera-cam1``, ``common_name("reader", "kitchen-tablet")`` -> ``reader-kitchen-tablet``.
    """
    if role in (ROUTER, FUSION):
        return role
    if role not in ("camera", "reader"):
        raise ValueError(f"role must be router, fusion, camera or reader, got {role!r}")
    return f"{role}-{keys.validate_chunk(name, f'{role} name')}"


def cert_path(folder: str | Path, host: str) -> Path:
    """``<folder>/<host>.pem``: a host's certificate (host: router, fusion, a camera id, a reader)."""
    return Path(folder) / f"{host}.pem"


def key_path(folder: str | Path, host: str) -> Path:
    """``<folder>/<host>-key.pem``: a host's private key."""
    return Path(folder) / f"{host}-key.pem"


@dataclass(frozen=True)
class HostCert:
    """One certificate written: its file stem, common name and alternative names."""

    host: str
    common_name: str
    names: tuple[str, ...]
    cert: Path
    key: Path


@dataclass(frozen=True)
class Made:
    """What :func:`make_site_certs` wrote."""

    folder: Path
    ca: Path
    ca_key: Path
    ca_reused: bool
    hosts: tuple[HostCert, ...]


def make_site_certs(
    folder: str | Path,
    *,
    site: str,
    cameras: Sequence[str],
    readers: Sequence[str] = DEFAULT_READERS,
    names: Mapping[str, Iterable[str]] | None = None,
    force: bool = False,
    reuse_ca: bool = False,
    days: int = DEFAULT_DAYS,
    now: _dt.datetime | None = None,
) -> Made:
    """Write the site's authority and the certificates of the router, the fusion host, each
    camera and each reader into ``folder``.

    ``names`` maps a host (``router``, ``fusion``, a camera id, a reader name, or ``*`` for
    every host) to extra DNS names or IP addresses for its certificate. An existing
    authority is never replaced unless ``force``; with ``reuse_ca`` it signs certificates for
    the hosts that have none in ``folder`` yet (the others keep theirs). ``now`` (UTC) is the
    start of validity (for tests).
    """
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

    if force and reuse_ca:
        raise CertError("give --force (a new authority) or --reuse-ca (keep it), not both")
    if not 1 <= days <= 36500:
        raise CertError(f"days must lie in 1..36500, got {days}")
    keys.validate_chunk(site, "site")
    hosts = _hosts(cameras, readers)
    extra = {h: [str(n) for n in ns] for h, ns in (names or {}).items()}
    unknown = sorted(set(extra) - set(hosts) - {"*"})
    if unknown:
        raise CertError(f"host names given for {', '.join(unknown)}, which is not a host of this site "
                        f"(hosts: {', '.join(hosts)}, or * for all)")
    out = Path(folder)
    ca_file, ca_key_file = out / CA_FILE, out / CA_KEY_FILE
    exists = ca_file.exists() or ca_key_file.exists()
    if exists and not (force or reuse_ca):
        raise CertError(f"{ca_file} already exists: give --reuse-ca to sign new host certificates with it, or "
                        "--force to replace the authority (then every host needs its new certificate)")
    if reuse_ca and not exists:
        raise CertError(f"--reuse-ca: no authority in {out} ({CA_FILE} and {CA_KEY_FILE})")
    out.mkdir(parents=True, exist_ok=True)
    start = (now or _dt.datetime.now(_dt.timezone.utc)) - _dt.timedelta(minutes=5)  # small clock differences
    end = start + _dt.timedelta(days=days)

    if reuse_ca:
        ca_cert = x509.load_pem_x509_certificate(ca_file.read_bytes())
        ca_key = serialization.load_pem_private_key(ca_key_file.read_bytes(), password=None)
    else:
        ca_key = ec.generate_private_key(ec.SECP256R1())
        ca_name = x509.Name([x509.NameAttribute(NameOID.ORGANIZATION_NAME, "voxelwatch"),
                             x509.NameAttribute(NameOID.COMMON_NAME, f"voxelwatch {site} authority")])
        ca_cert = (
            x509.CertificateBuilder().subject_name(ca_name).issuer_name(ca_name)
            .public_key(ca_key.public_key()).serial_number(x509.random_serial_number())
            .not_valid_before(start).not_valid_after(end)
            .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
            .add_extension(x509.KeyUsage(digital_signature=True, key_cert_sign=True, crl_sign=True,
                                         content_commitment=False, key_encipherment=False,
                                         data_encipherment=False, key_agreement=False,
                                         encipher_only=False, decipher_only=False), critical=True)
            .add_extension(x509.SubjectKeyIdentifier.from_public_key(ca_key.public_key()), critical=False)
            .sign(ca_key, hashes.SHA256())
        )
        _write_key(ca_key_file, ca_key)
        ca_file.write_bytes(ca_cert.public_bytes(serialization.Encoding.PEM))

    made = []
    for host, cn in hosts.items():
        if reuse_ca and cert_path(out, host).exists() and key_path(out, host).exists():
            continue  # a host that already has its files keeps them
        alt = _unique([*LOCAL_NAMES, *extra.get("*", []), *extra.get(host, [])])
        key = ec.generate_private_key(ec.SECP256R1())
        cert = (
            x509.CertificateBuilder()
            .subject_name(x509.Name([x509.NameAttribute(NameOID.ORGANIZATION_NAME, f"voxelwatch {site}"),
                                     x509.NameAttribute(NameOID.COMMON_NAME, cn)]))
            .issuer_name(ca_cert.subject).public_key(key.public_key())
            .serial_number(x509.random_serial_number()).not_valid_before(start).not_valid_after(end)
            .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
            .add_extension(x509.SubjectAlternativeName([_general_name(n) for n in alt]), critical=False)
            .add_extension(x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH,
                                                  ExtendedKeyUsageOID.CLIENT_AUTH]), critical=False)
            .add_extension(x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_key.public_key()), critical=False)
            .sign(ca_key, hashes.SHA256())
        )
        c, k = cert_path(out, host), key_path(out, host)
        _write_key(k, key)
        c.write_bytes(cert.public_bytes(serialization.Encoding.PEM))
        made.append(HostCert(host=host, common_name=cn, names=tuple(alt), cert=c, key=k))
    return Made(folder=out, ca=ca_file, ca_key=ca_key_file, ca_reused=reuse_ca, hosts=tuple(made))


def read_common_name(path: str | Path) -> str:
    """The subject common name of the PEM certificate at ``path``."""
    from cryptography import x509
    from cryptography.x509.oid import NameOID

    cert = x509.load_pem_x509_certificate(Path(path).read_bytes())
    found = cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)
    return str(found[0].value) if found else ""


def where_to_copy(made: Made) -> list[str]:
    """One line per host: which files go to which host (for the command's output)."""
    lines = []
    for h in made.hosts:
        role = ("the fusion host (router)" if h.host == ROUTER else "the fusion host" if h.host == FUSION
                else f"reader {h.host}" if h.common_name.startswith("reader-") else f"camera host {h.host}")
        lines.append(f"{role}: {made.ca.name}, {h.cert.name}, {h.key.name}  (known as {h.common_name}; "
                     f"names {', '.join(h.names)})")
    return lines


def _hosts(cameras: Sequence[str], readers: Sequence[str]) -> dict[str, str]:
    """File stem -> common name for every host; CertError on a clash."""
    hosts = {ROUTER: common_name(ROUTER), FUSION: common_name(FUSION)}
    for role, names in (("camera", cameras), ("reader", readers)):
        for name in names:
            if name in hosts:
                raise CertError(f"{role} {name!r}: the name is taken by another host of the site")
            hosts[name] = common_name(role, name)
    return hosts


def _general_name(name: str):
    from cryptography import x509

    try:
        return x509.IPAddress(ipaddress.ip_address(name))
    except ValueError:
        return x509.DNSName(name)


def _unique(items: Iterable[str]) -> list[str]:
    seen: list[str] = []
    for item in items:
        if item and item not in seen:
            seen.append(item)
    return seen


def _write_key(path: Path, key) -> None:
    """Write a private key readable by its owner only (created 0600, never widened)."""
    from cryptography.hazmat.primitives import serialization

    data = key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                             serialization.NoEncryption())
    path.unlink(missing_ok=True)
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(fd, "wb") as f:
        f.write(data)
    os.chmod(path, 0o600)  # whatever the umask

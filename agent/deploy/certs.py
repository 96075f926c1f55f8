"""A site's certificate authority and one certificate per host, with ``cryptography``.

Zenoh's TLS (rustls) authenticates both ends of every link against the site CA
(``enable_mtls``), and its access control identifies a remote by the common name of the
certificate it presented (``cert_common_names``).  So the common name of a host's
certificate *is* its identity: the agent id of an agent host, the name of a client host,
the name of the router.  Each certificate also names its host (DNS) and any address it is
reached at (IP) as subject alternative names, because rustls checks the name the
connecting side dialled against them (``verify_name_on_connect``), never the common name.

Layout written by :func:`create_site` under ``DIR``::

    DIR/site.json              the site: name, router, agent hosts, client hosts
    DIR/ca/ca.key              the CA's private key: keep it off the hosts
    DIR/ca/ca.pem              the CA's certificate
    DIR/hosts/NAME/ca.pem      a copy of the CA certificate (what a host trusts)
    DIR/hosts/NAME/cert.pem    the host's certificate (CN = NAME)
    DIR/hosts/NAME/key.pem     the host's private key (mode 0600)

``DIR/hosts/NAME`` is everything host NAME needs; copy it there.  Keys are ECDSA P-256
(accepted by rustls, small and fast to handshake).
"""

from __future__ import annotations

import datetime as dt
import ipaddress
import json
import os
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path

from agent.errors import UmaError
from schemas.ids import check_id

try:
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID
except ImportError:  # pragma: no cover - depends on the installed extras
    x509 = None  # type: ignore[assignment]

SITE_FILE = "site.json"


@dataclass
class SiteSpec:
    """Who belongs to a site and in which role: what the certificates and the access
    control are made from."""

    site: str
    router: str
    hosts: list[str]
    clients: list[str] = field(default_factory=list)
    #: extra subject alternative names per member (addresses it is reached at)
    addresses: dict[str, list[str]] = field(default_factory=dict)

    def check(self) -> SiteSpec:
        """Every name a valid uma id, no name twice; ``UmaError`` says which."""
        if not self.hosts:
            raise UmaError("a site needs at least one agent host (--hosts a,b,c)")
        names = [self.router, *self.hosts, *self.clients]
        for name in names:
            try:
                check_id("host name", name)
            except ValueError as exc:
                raise UmaError(str(exc)) from None
        twice = sorted({n for n in names if names.count(n) > 1})
        if twice:
            raise UmaError(f"each host has one role; named twice: {', '.join(twice)}")
        unknown = sorted(set(self.addresses) - set(names))
        if unknown:
            raise UmaError(f"--address for unknown host(s): {', '.join(unknown)}")
        for addrs in self.addresses.values():
            for addr in addrs:
                _san(addr)  # raises on a malformed one
        return self

    @property
    def members(self) -> list[str]:
        return [self.router, *self.hosts, *self.clients]


def load_site(directory: str | Path) -> SiteSpec:
    """The site written by :func:`create_site` in ``directory``."""
    path = Path(directory) / SITE_FILE
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
        return SiteSpec(**data).check()
    except FileNotFoundError:
        raise UmaError(f"{path} does not exist: run 'uma deploy certs {directory} ...' "
                       "first") from None
    except (ValueError, TypeError) as exc:
        raise UmaError(f"{path} is not a site description: {exc}") from None


def create_site(directory: str | Path, spec: SiteSpec, days: int = 825) -> Path:
    """Write the CA and every member's certificate and key under ``directory`` (see the
    module docstring); refuses to overwrite an existing CA, whose loss would orphan every
    certificate it signed."""
    if x509 is None:
        raise UmaError("certificates need the 'cryptography' package: "
                       "pip install 'uma-tracking[site]'")
    spec.check()
    if not 1 <= days <= 36500:
        raise UmaError(f"--days must be in 1..36500, got {days}")
    root = Path(directory)
    ca_dir = root / "ca"
    if (ca_dir / "ca.key").exists():
        raise UmaError(f"{ca_dir / 'ca.key'} exists already: this directory holds a site; "
                       "choose another one")
    ca_key = ec.generate_private_key(ec.SECP256R1())
    ca_cert = _ca_certificate(ca_key, spec.site, days)
    _write_key(ca_dir / "ca.key", ca_key)
    _write(ca_dir / "ca.pem", _pem(ca_cert))
    for name in spec.members:
        key = ec.generate_private_key(ec.SECP256R1())
        cert = _host_certificate(key, name, spec.addresses.get(name, []), ca_key, ca_cert,
                                 days)
        host = root / "hosts" / name
        _write(host / "ca.pem", _pem(ca_cert))
        _write(host / "cert.pem", _pem(cert))
        _write_key(host / "key.pem", key)
    _write(root / SITE_FILE, json.dumps(asdict(spec), indent=2).encode() + b"\n")
    return root


def _ca_certificate(key: ec.EllipticCurvePrivateKey, site: str, days: int
                    ) -> x509.Certificate:
    name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, f"uma site {site} CA"),
                      x509.NameAttribute(NameOID.ORGANIZATION_NAME, f"uma site {site}")])
    return (_builder(name, name, key.public_key(), days * 4)
            .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
            .add_extension(x509.KeyUsage(digital_signature=True, key_cert_sign=True,
                                         crl_sign=True, content_commitment=False,
                                         key_encipherment=False, data_encipherment=False,
                                         key_agreement=False, encipher_only=False,
                                         decipher_only=False), critical=True)
            .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()),
                           critical=False)
            .sign(key, hashes.SHA256()))


def _host_certificate(key: ec.EllipticCurvePrivateKey, name: str, addresses: Sequence[str],
                      ca_key: ec.EllipticCurvePrivateKey, ca_cert: x509.Certificate,
                      days: int) -> x509.Certificate:
    subject = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, name)])
    sans = [x509.DNSName(name), *(_san(a) for a in addresses)]
    return (_builder(subject, ca_cert.subject, key.public_key(), days)
            .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
            .add_extension(x509.SubjectAlternativeName(sans), critical=False)
            .add_extension(x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH,
                                                  ExtendedKeyUsageOID.CLIENT_AUTH]),
                           critical=False)
            .add_extension(x509.AuthorityKeyIdentifier.from_issuer_public_key(
                ca_key.public_key()), critical=False)
            .sign(ca_key, hashes.SHA256()))


def _builder(subject: x509.Name, issuer: x509.Name, public_key: object, days: int
             ) -> x509.CertificateBuilder:
    now = dt.datetime.now(dt.UTC)
    return (x509.CertificateBuilder().subject_name(subject).issuer_name(issuer)
            .public_key(public_key).serial_number(x509.random_serial_number())
            .not_valid_before(now - dt.timedelta(hours=1))  # hosts' clocks differ a little
            .not_valid_after(now + dt.timedelta(days=days)))


def _san(address: str) -> x509.GeneralName:
    """An IP address SAN, or a DNS name SAN for anything else that is a host name."""
    try:
        return x509.IPAddress(ipaddress.ip_address(address))
    except ValueError:
        pass
    if not address or any(c in address for c in " /:@*") or len(address) > 253:
        raise UmaError(f"address {address!r} is neither an IP address nor a host name")
    return x509.DNSName(address)


def _pem(cert: x509.Certificate) -> bytes:
    return cert.public_bytes(serialization.Encoding.PEM)


def _write(path: Path, data: bytes, mode: int = 0o644) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, mode)
    with os.fdopen(fd, "wb") as f:
        f.write(data)
    os.chmod(path, mode)


def _write_key(path: Path, key: ec.EllipticCurvePrivateKey) -> None:
    _write(path, key.private_bytes(serialization.Encoding.PEM,
                                   serialization.PrivateFormat.PKCS8,
                                   serialization.NoEncryption()), mode=0o600)

"""The cloud's certificate authority, made with the `cryptography` library: pure functions of keys and a clock."""

from __future__ import annotations

import base64
import hashlib
import ipaddress
import secrets
from collections.abc import Iterable
from datetime import datetime, timedelta

from cryptography import x509
from cryptography.fernet import Fernet, InvalidToken
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

__all__ = [
    "SEALED",
    "SealError",
    "issue",
    "key_pem",
    "load_cert",
    "load_key",
    "make_ca",
    "make_crl",
    "new_key",
    "pem",
    "seal",
    "sealing_key",
    "tls_crypt_key",
    "unseal",
]

Key = ec.EllipticCurvePrivateKey

# What a sealed secret starts with; a PEM never does, so plain rows from before sealing are told apart.
SEALED = "sealed:fernet:"


class SealError(ValueError):
    """A sealed secret cannot be opened: the sealing key is not the one it was sealed with."""


def new_key() -> Key:
    """Make a P-256 key: small, fast, and what OpenVPN and browsers handle everywhere."""
    return ec.generate_private_key(ec.SECP256R1())


def _name(common_name: str) -> x509.Name:
    organisation = x509.NameAttribute(NameOID.ORGANIZATION_NAME, "bridgeOS")
    return x509.Name([organisation, x509.NameAttribute(NameOID.COMMON_NAME, common_name)])


def make_ca(common_name: str, *, now: datetime, days: int = 3650) -> tuple[Key, x509.Certificate]:
    """Make a self-signed CA that may sign certificates but not other CAs."""
    key = new_key()
    cert = (
        x509.CertificateBuilder()
        .subject_name(_name(common_name))
        .issuer_name(_name(common_name))
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - timedelta(minutes=5))
        .not_valid_after(now + timedelta(days=days))
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .add_extension(
            x509.KeyUsage(False, False, False, False, False, True, True, False, False), critical=True
        )  # keyCertSign, cRLSign
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
        .sign(key, hashes.SHA256())
    )
    return key, cert


def issue(
    ca_key: Key,
    ca_cert: x509.Certificate,
    common_name: str,
    *,
    server: bool,
    now: datetime,
    names: Iterable[str] = (),
    days: int = 825,
) -> tuple[Key, x509.Certificate]:
    """Issue a server (serverAuth, with names) or client (clientAuth) certificate and its new key."""
    key = new_key()
    usage = ExtendedKeyUsageOID.SERVER_AUTH if server else ExtendedKeyUsageOID.CLIENT_AUTH
    builder = (
        x509.CertificateBuilder()
        .subject_name(_name(common_name))
        .issuer_name(ca_cert.subject)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - timedelta(minutes=5))
        .not_valid_after(now + timedelta(days=days))
        .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
        .add_extension(
            x509.KeyUsage(True, False, True, False, True, False, False, False, False), critical=True
        )  # digitalSignature, keyEncipherment, keyAgreement
        .add_extension(x509.ExtendedKeyUsage([usage]), critical=False)
        .add_extension(x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_key.public_key()), critical=False)
    )
    alternatives: list[x509.GeneralName] = []
    for name in names:
        try:
            alternatives.append(x509.IPAddress(ipaddress.ip_address(name)))
        except ValueError:
            alternatives.append(x509.DNSName(name))
    if alternatives:
        builder = builder.add_extension(x509.SubjectAlternativeName(alternatives), critical=False)
    return key, builder.sign(ca_key, hashes.SHA256())


def make_crl(
    ca_key: Key, ca_cert: x509.Certificate, revoked: Iterable[tuple[int, datetime]], *, now: datetime, days: int = 30
) -> x509.CertificateRevocationList:
    """Sign a CRL listing the revoked serials; OpenVPN refuses every peer whose CRL is out of date."""
    builder = (
        x509.CertificateRevocationListBuilder()
        .issuer_name(ca_cert.subject)
        .last_update(now - timedelta(minutes=5))
        .next_update(now + timedelta(days=days))
    )
    for serial, when in revoked:
        builder = builder.add_revoked_certificate(
            x509.RevokedCertificateBuilder().serial_number(serial).revocation_date(when).build()
        )
    return builder.sign(ca_key, hashes.SHA256())


def pem(obj: x509.Certificate | x509.CertificateRevocationList) -> str:
    """Return a certificate or CRL as PEM text."""
    return obj.public_bytes(serialization.Encoding.PEM).decode()


def key_pem(key: Key) -> str:
    """Return a private key as unencrypted PKCS#8 PEM text (sealed in the database, served only to its owner)."""
    return key.private_bytes(
        serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()
    ).decode()


def load_key(text: str) -> Key:
    """Load a private key from PEM text."""
    key = serialization.load_pem_private_key(text.encode(), password=None)
    assert isinstance(key, ec.EllipticCurvePrivateKey)
    return key


def load_cert(text: str) -> x509.Certificate:
    """Load a certificate from PEM text."""
    return x509.load_pem_x509_certificate(text.encode())


def tls_crypt_key() -> str:
    """Make an OpenVPN static key (2048 bits) for tls-crypt: the control channel is encrypted and unforgeable."""
    body = secrets.token_hex(256)
    lines = [body[i : i + 32] for i in range(0, len(body), 32)]
    return "-----BEGIN OpenVPN Static key V1-----\n" + "\n".join(lines) + "\n-----END OpenVPN Static key V1-----\n"


def sealing_key(secret: str) -> Fernet:
    """Make the Fernet that seals secrets at rest: ``secret`` is a Fernet key, or any passphrase (its SHA-256)."""
    try:
        return Fernet(secret.strip().encode())
    except ValueError:
        return Fernet(base64.urlsafe_b64encode(hashlib.sha256(secret.encode()).digest()))


def seal(text: str, fernet: Fernet) -> str:
    """Encrypt and authenticate a secret (AES-128-CBC + HMAC-SHA256) for storing; sealed text is kept as is."""
    if text.startswith(SEALED):
        return text
    return SEALED + fernet.encrypt(text.encode()).decode()


def unseal(text: str, fernet: Fernet) -> str:
    """Open a sealed secret; plain text (stored before sealing existed) is returned as is."""
    if not text.startswith(SEALED):
        return text
    try:
        return fernet.decrypt(text[len(SEALED) :].encode()).decode()
    except InvalidToken:
        raise SealError(
            "a private key of the VPN PKI cannot be unsealed: BRIDGEOS_PKI_KEY (or the generated"
            " pki_key in the data dir) is not the key it was sealed with"
        ) from None

"""Make the deployed stack's keys and certificates: the cloud's CA, the registry's and the load balancer's TLS.

scripts/deploy.sh runs it in a throwaway bridgeos/cloud container with the secrets directory mounted:

    python3 stack_pki.py DIR --lb-names NAME,NAME... REGISTRY_NAME...

It writes, each only when missing, DIR/ca.crt and DIR/ca_key (the cloud's CA: the cloud adopts it at
its first start, docker/cloud/migrate_locked.py), DIR/registry_key (the P-256 key that signs registry
tokens, shared by the cloud and the registry's certificate bundle) and DIR/registry_tls.crt and .key
(the registry's certificate, issued by that CA for the REGISTRY_NAMEs). A registry certificate issued
for other names is refused with the way out, rather than silently replaced: its secrets keep their
names, and Swarm secrets cannot change in place.

Then DIR/lb.pem, the load balancer's certificate chain and key: the operator's (DIR/lb_given.crt and
.key, copied there by deploy.sh) once checked, else one issued by the CA for the --lb-names, issued
again when those names change (the stack names that secret by its content's hash). Last, it prints the
CA's SHA-256 fingerprint.
"""

from __future__ import annotations

import argparse
import sys
from datetime import UTC, datetime
from pathlib import Path

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization

from network import pki


def write(path: Path, text: str) -> None:
    """Write a secret file readable by its owner only."""
    path.touch(mode=0o600)
    path.write_text(text)


def fingerprint(cert: x509.Certificate) -> str:
    """Return a certificate's SHA-256 fingerprint as colon-separated hex, as openssl prints it."""
    return ":".join(f"{byte:02X}" for byte in cert.fingerprint(hashes.SHA256()))


def registry_files(directory: Path, names: list[str], now: datetime) -> None:
    """Make the token key and the registry's certificate once, and refuse a change of its names."""
    ca_cert, ca_key = directory / "ca.crt", directory / "ca_key"
    token_key = directory / "registry_key"
    if not token_key.exists():
        write(token_key, pki.key_pem(pki.new_key()))
    tls_cert, tls_key, tls_names = (directory / f"registry_tls.{end}" for end in ("crt", "key", "names"))
    wanted = "\n".join(names) + "\n"
    if tls_cert.exists() and tls_names.exists():
        if tls_names.read_text() != wanted:
            sys.exit(
                f"stack_pki: the registry's certificate was issued for {tls_names.read_text().split()}, not {names}:"
                f" to change them, run scripts/deploy.sh down, delete {directory}/registry_tls.*, and deploy again"
            )
        return
    key, cert = pki.issue(
        pki.load_key(ca_key.read_text()),
        pki.load_cert(ca_cert.read_text()),
        names[0],
        server=True,
        now=now,
        names=names,
    )
    write(tls_key, pki.key_pem(key))
    write(tls_cert, pki.pem(cert))
    tls_names.write_text(wanted)


def given_pem(cert_file: Path, key_file: Path, now: datetime) -> str:
    """Return the operator's certificate chain and key as one PEM, or exit saying what is wrong with them."""
    try:
        chain = x509.load_pem_x509_certificates(cert_file.read_bytes())
    except ValueError as exc:
        sys.exit(f"stack_pki: BRIDGEOS_DEPLOY_TLS_CERT is not a PEM certificate (chain): {exc}")
    try:
        key = serialization.load_pem_private_key(key_file.read_bytes(), password=None)
    except (ValueError, TypeError) as exc:
        sys.exit(f"stack_pki: BRIDGEOS_DEPLOY_TLS_KEY is not an unencrypted PEM private key: {exc}")
    leaf = chain[0]
    public = serialization.PublicFormat.SubjectPublicKeyInfo
    if key.public_key().public_bytes(serialization.Encoding.PEM, public) != leaf.public_key().public_bytes(
        serialization.Encoding.PEM, public
    ):
        sys.exit("stack_pki: BRIDGEOS_DEPLOY_TLS_KEY is not the key of BRIDGEOS_DEPLOY_TLS_CERT's first certificate")
    if leaf.not_valid_after_utc <= now:
        sys.exit(f"stack_pki: BRIDGEOS_DEPLOY_TLS_CERT expired on {leaf.not_valid_after_utc:%Y-%m-%d}")
    key_text = key.private_bytes(
        serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()
    ).decode()
    return "".join(pki.pem(cert) for cert in chain) + key_text


def lb_files(directory: Path, names: list[str], now: datetime) -> None:
    """Write lb.pem: the operator's pair, else a certificate from the CA for the names (again if they changed)."""
    given_cert, given_key = directory / "lb_given.crt", directory / "lb_given.key"
    lb_pem = directory / "lb.pem"
    if given_cert.exists() and given_key.exists():
        write(lb_pem, given_pem(given_cert, given_key, now))
        return
    tls_names = directory / "lb_tls.names"
    wanted = "\n".join(names) + "\n"
    if lb_pem.exists() and tls_names.exists() and tls_names.read_text() == wanted:
        cert = x509.load_pem_x509_certificate(lb_pem.read_bytes())
        if pki.load_cert((directory / "ca.crt").read_text()).subject == cert.issuer:
            return  # issued here before, not the operator's pair of an earlier deploy
    key, cert = pki.issue(
        pki.load_key((directory / "ca_key").read_text()),
        pki.load_cert((directory / "ca.crt").read_text()),
        names[0],
        server=True,
        now=now,
        names=names,
    )
    write(lb_pem, pki.pem(cert) + pki.key_pem(key))
    tls_names.write_text(wanted)


def main(argv: list[str] | None = None) -> None:
    """Make what is missing, then print the CA's fingerprint."""
    parser = argparse.ArgumentParser(prog="stack_pki.py", description=__doc__.splitlines()[0])
    parser.add_argument("directory", type=Path)
    parser.add_argument("registry_names", nargs="+", metavar="REGISTRY_NAME")
    parser.add_argument("--lb-names", required=True, help="comma-separated names and addresses of the stack")
    args = parser.parse_args(argv)
    lb_names = [name.strip() for name in args.lb_names.split(",") if name.strip()]
    if not lb_names:
        parser.error("--lb-names: give the names and addresses robots and browsers reach the stack by")
    directory: Path = args.directory
    now = datetime.now(UTC)
    ca_cert, ca_key = directory / "ca.crt", directory / "ca_key"
    if not ca_cert.exists() or not ca_key.exists():
        key, cert = pki.make_ca("bridgeOS cloud CA", now=now)
        write(ca_key, pki.key_pem(key))
        write(ca_cert, pki.pem(cert))
        ca_cert.chmod(0o644)
    registry_files(directory, args.registry_names, now)
    lb_files(directory, lb_names, now)
    print(fingerprint(pki.load_cert(ca_cert.read_text())))


if __name__ == "__main__":
    main()

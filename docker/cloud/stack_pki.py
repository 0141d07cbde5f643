"""Make the deployed stack's keys and certificates once: the cloud's CA, the registry's TLS certificate, the token key.

scripts/deploy.sh runs it in a throwaway bridgeos/cloud container with the secrets directory mounted:

    python3 stack_pki.py DIR NAME...

It writes, each only when missing, DIR/ca.crt and DIR/ca_key (the cloud's CA: the cloud adopts it at
its first start, docker/cloud/migrate_locked.py), DIR/registry_key (the P-256 key that signs registry
tokens, shared by the cloud and the registry's certificate bundle) and DIR/registry_tls.crt and .key
(the registry's certificate, issued by that CA for the NAMEs). A certificate issued for other names is
refused with the way out, rather than silently replaced: Swarm secrets cannot change in place.
"""

from __future__ import annotations

import sys
from datetime import UTC, datetime
from pathlib import Path

from network import pki


def write(path: Path, text: str) -> None:
    """Write a secret file readable by its owner only."""
    path.touch(mode=0o600)
    path.write_text(text)


def main(directory: Path, names: list[str]) -> None:
    """Make what is missing and check the registry certificate names what was asked."""
    if not names:
        sys.exit("stack_pki: give the names the registry's certificate must carry")
    now = datetime.now(UTC)
    ca_cert, ca_key = directory / "ca.crt", directory / "ca_key"
    if not ca_cert.exists() or not ca_key.exists():
        key, cert = pki.make_ca("bridgeOS cloud CA", now=now)
        write(ca_key, pki.key_pem(key))
        write(ca_cert, pki.pem(cert))
        ca_cert.chmod(0o644)
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


if __name__ == "__main__":
    if len(sys.argv) < 2:
        sys.exit(__doc__)
    main(Path(sys.argv[1]), sys.argv[2:])

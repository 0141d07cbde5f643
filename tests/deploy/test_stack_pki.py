"""docker/cloud/stack_pki.py, run as deploy.sh runs it: the stack's CA, the registry's and the load balancer's TLS."""

from __future__ import annotations

import os
import ssl
import subprocess
import sys
from datetime import UTC, datetime, timedelta
from pathlib import Path

from cryptography import x509
from cryptography.hazmat.primitives import hashes

from network import pki
from tests.conftest import ROOT

SCRIPT = ROOT / "docker" / "cloud" / "stack_pki.py"


def stack_pki(directory: Path, *args: str) -> subprocess.CompletedProcess[str]:
    """Run the script as the cloud image does (the project's root on the path)."""
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    return subprocess.run(
        [sys.executable, str(SCRIPT), str(directory), *args], capture_output=True, text=True, env=env, timeout=60
    )


def lb_chain(directory: Path) -> list[x509.Certificate]:
    return x509.load_pem_x509_certificates((directory / "lb.pem").read_bytes())


def verifies(directory: Path, name: str) -> bool:
    """Whether a TLS handshake for the name, with lb.pem served and the stack's CA trusted, succeeds."""
    server = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
    server.load_cert_chain(directory / "lb.pem")
    client = ssl.create_default_context(cafile=directory / "ca.crt")
    near, far = ssl.MemoryBIO(), ssl.MemoryBIO()
    ends = (client.wrap_bio(near, far, server_hostname=name), server.wrap_bio(far, near, server_side=True))
    for _ in range(10):
        for end in ends:
            try:
                end.do_handshake()
            except ssl.SSLWantReadError:
                continue
            except ssl.SSLCertVerificationError:
                return False
    return ends[0].version() is not None


def test_the_lb_certificate_is_issued_from_the_clouds_ca_for_the_deployments_names(tmp_path: Path) -> None:
    made = stack_pki(tmp_path, "--lb-names", "cloud.example,10.0.0.5,127.0.0.1", "vm", "registry")
    assert made.returncode == 0, made.stderr
    ca = x509.load_pem_x509_certificate((tmp_path / "ca.crt").read_bytes())
    fingerprint = ":".join(f"{byte:02X}" for byte in ca.fingerprint(hashes.SHA256()))
    assert made.stdout.strip() == fingerprint
    (leaf,) = lb_chain(tmp_path)
    assert leaf.issuer == ca.subject
    assert verifies(tmp_path, "cloud.example") and verifies(tmp_path, "10.0.0.5")
    assert not verifies(tmp_path, "elsewhere.example")
    assert oct((tmp_path / "lb.pem").stat().st_mode & 0o777) == "0o600"

    # Deployed again with the same names: the same certificate (the stack's secret does not change) ...
    same = (tmp_path / "lb.pem").read_text()
    assert stack_pki(tmp_path, "--lb-names", "cloud.example,10.0.0.5,127.0.0.1", "vm", "registry").returncode == 0
    assert (tmp_path / "lb.pem").read_text() == same
    # ... with other names, a new one from the same CA, while the registry's stays what it was.
    registry = (tmp_path / "registry_tls.crt").read_text()
    assert stack_pki(tmp_path, "--lb-names", "cloud.example,other.example", "vm", "registry").returncode == 0
    assert (tmp_path / "lb.pem").read_text() != same and verifies(tmp_path, "other.example")
    assert (tmp_path / "registry_tls.crt").read_text() == registry


def test_the_operators_own_certificate_is_checked_then_served(tmp_path: Path) -> None:
    now = datetime.now(UTC)
    issuer_key, issuer = pki.make_ca("the operator's CA", now=now)
    key, cert = pki.issue(issuer_key, issuer, "cloud.example", server=True, now=now, names=["cloud.example"])
    (tmp_path / "lb_given.crt").write_text(pki.pem(cert) + pki.pem(issuer))
    (tmp_path / "lb_given.key").write_text(pki.key_pem(key))
    made = stack_pki(tmp_path, "--lb-names", "ignored.example", "vm", "registry")
    assert made.returncode == 0, made.stderr
    assert [c.subject for c in lb_chain(tmp_path)] == [cert.subject, issuer.subject]

    # A key that is not the certificate's, or a certificate past its date, is refused saying which.
    (tmp_path / "lb_given.key").write_text(pki.key_pem(pki.new_key()))
    wrong = stack_pki(tmp_path, "--lb-names", "ignored.example", "vm", "registry")
    assert wrong.returncode == 1
    assert "BRIDGEOS_DEPLOY_TLS_KEY is not the key of BRIDGEOS_DEPLOY_TLS_CERT's first certificate" in wrong.stderr
    old_key, old = pki.issue(issuer_key, issuer, "cloud.example", server=True, now=now - timedelta(days=900))
    (tmp_path / "lb_given.crt").write_text(pki.pem(old))
    (tmp_path / "lb_given.key").write_text(pki.key_pem(old_key))
    expired = stack_pki(tmp_path, "--lb-names", "ignored.example", "vm", "registry")
    assert expired.returncode == 1 and "BRIDGEOS_DEPLOY_TLS_CERT expired on" in expired.stderr
    (tmp_path / "lb_given.crt").write_text("not a certificate\n")
    garbled = stack_pki(tmp_path, "--lb-names", "ignored.example", "vm", "registry")
    assert garbled.returncode == 1 and "BRIDGEOS_DEPLOY_TLS_CERT is not a PEM certificate" in garbled.stderr

    # Without the operator's files again, the CA issues one for the names.
    for given in ("lb_given.crt", "lb_given.key"):
        (tmp_path / given).unlink()
    assert stack_pki(tmp_path, "--lb-names", "cloud.example", "vm", "registry").returncode == 0
    assert verifies(tmp_path, "cloud.example")

"""`manage.py registry_config` writes a working registry config and the token certificate, or nothing at all."""

from __future__ import annotations

import shutil
import ssl
from datetime import UTC, datetime

import httpx
import pytest
import yaml
from cryptography import x509
from django.core.management import CommandError, call_command

from network import pki
from registry import services
from registry.tokens import key_id
from tests.conftest import free_port

from .conftest import serving

REALM = "http://127.0.0.1:8000/api/registry/token"


def configure(tmp_path, **options):
    arguments = {"realm": REALM, "listen": "127.0.0.1:5000", "storage": str(tmp_path / "store")}
    call_command("registry_config", out=str(tmp_path / "out"), stdout=None, **{**arguments, **options})
    return yaml.safe_load((tmp_path / "out" / "config.yml").read_text())


def test_a_loopback_registry_gets_plain_http_and_token_auth_against_the_realm(tmp_path):
    config = configure(tmp_path, service="reg-1", issuer="cloud-1")
    assert config["version"] == "0.1"
    assert config["storage"]["filesystem"]["rootdirectory"] == str(tmp_path / "store")
    assert config["http"]["addr"] == "127.0.0.1:5000" and "tls" not in config["http"]
    assert config["auth"] == {
        "token": {
            "realm": REALM,
            "service": "reg-1",
            "issuer": "cloud-1",
            "rootcertbundle": str(tmp_path / "out" / "token.crt"),
        }
    }
    cert = x509.load_pem_x509_certificate((tmp_path / "out" / "token.crt").read_bytes())
    assert key_id(cert.public_key()) == key_id(services.signing_key().public_key())


def test_the_defaults_are_the_clouds_issuer_and_service(tmp_path, settings):
    config = configure(tmp_path, listen="[::1]:5000")
    assert config["auth"]["token"]["issuer"] == settings.BRIDGEOS["REGISTRY_ISSUER"] == "bridgeos-cloud"
    assert config["auth"]["token"]["service"] == settings.BRIDGEOS["REGISTRY_SERVICE"]


@pytest.mark.skipif(shutil.which("docker-registry") is None, reason="docker-registry is not installed")
def test_the_registry_serves_https_with_a_certificate_of_the_clouds_ca(tmp_path):
    now = datetime.now(UTC)
    ca_key, ca = pki.make_ca("test CA", now=now)
    key, cert = pki.issue(ca_key, ca, "127.0.0.1", server=True, now=now, names=["127.0.0.1"])
    (tmp_path / "ca.crt").write_text(pki.pem(ca))
    (tmp_path / "tls.crt").write_text(pki.pem(cert))
    (tmp_path / "tls.key").write_text(pki.key_pem(key))
    host = f"127.0.0.1:{free_port()}"
    configure(tmp_path, listen=host, tls_cert=str(tmp_path / "tls.crt"), tls_key=str(tmp_path / "tls.key"))
    with serving(tmp_path / "out" / "config.yml", host, tmp_path / "registry.log"):
        answer = httpx.get(f"https://{host}/v2/", verify=ssl.create_default_context(cafile=tmp_path / "ca.crt"))
    assert answer.status_code == 401
    assert answer.headers["WWW-Authenticate"] == f'Bearer realm="{REALM}",service="bridgeos-registry"'


def test_a_public_address_with_a_certificate_serves_tls(tmp_path):
    (tmp_path / "tls.crt").write_text("cert")
    (tmp_path / "tls.key").write_text("key")
    config = configure(
        tmp_path, listen="0.0.0.0:5000", tls_cert=str(tmp_path / "tls.crt"), tls_key=str(tmp_path / "tls.key")
    )
    assert config["http"]["tls"] == {"certificate": str(tmp_path / "tls.crt"), "key": str(tmp_path / "tls.key")}


@pytest.mark.parametrize(
    ("options", "message"),
    [
        ({"listen": "0.0.0.0:5000"}, "not a loopback address: give --tls-cert"),
        ({"listen": "registry.example.com:443"}, "not a loopback address"),
        ({"listen": "5000"}, "is not HOST:PORT"),
        ({"listen": "127.0.0.1:99999"}, "is not HOST:PORT"),
        ({"listen": ":5000"}, "is not HOST:PORT"),
        ({"realm": "ftp://cloud/token"}, "is not an http(s) URL"),
        ({"realm": "cloud/api/registry/token"}, "is not an http(s) URL"),
        ({"tls_cert": "/nonexistent/tls.crt"}, "does not exist"),
        ({"service": ""}, "must not be empty"),
    ],
)
def test_bad_input_is_a_clear_error_and_nothing_is_written(tmp_path, options, message):
    with pytest.raises(CommandError, match=message.replace("(", r"\(").replace(")", r"\)")):
        configure(tmp_path, **options)
    assert not (tmp_path / "out").exists()


def test_a_certificate_without_its_key_is_refused(tmp_path):
    (tmp_path / "tls.crt").write_text("cert")
    with pytest.raises(CommandError, match="go together"):
        configure(tmp_path, listen="0.0.0.0:5000", tls_cert=str(tmp_path / "tls.crt"))
    assert not (tmp_path / "out").exists()


def test_an_out_path_that_is_a_file_is_refused(tmp_path):
    (tmp_path / "out").write_text("")
    with pytest.raises(CommandError, match="not a directory"):
        configure(tmp_path)


@pytest.fixture
def registry_key(settings):
    """Let a test set BRIDGEOS_REGISTRY_KEY; the cached key is forgotten before and after."""
    services.signing_key.cache_clear()
    yield lambda pem: settings.BRIDGEOS.__setitem__("REGISTRY_KEY", pem)
    settings.BRIDGEOS["REGISTRY_KEY"] = ""
    services.signing_key.cache_clear()


def test_a_configured_key_signs_and_a_bad_one_is_a_clear_error(tmp_path, registry_key):
    key = pki.new_key()
    registry_key(pki.key_pem(key))
    configure(tmp_path)
    cert = x509.load_pem_x509_certificate((tmp_path / "out" / "token.crt").read_bytes())
    assert key_id(cert.public_key()) == key_id(key.public_key())
    services.signing_key.cache_clear()
    registry_key("not a key")
    with pytest.raises(CommandError, match="BRIDGEOS_REGISTRY_KEY is not an unencrypted PEM EC private key"):
        configure(tmp_path / "again")
    assert not (tmp_path / "again" / "out").exists()

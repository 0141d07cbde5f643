"""The PKI, OpenVPN's files and both sides' firewall rules, checked by OpenSSL's verifier and by nft itself."""

from __future__ import annotations

import importlib
import subprocess
from datetime import UTC, datetime

import pytest
from cryptography import x509
from cryptography.x509.oid import ExtendedKeyUsageOID
from django.apps import apps
from django.contrib.auth import get_user_model
from django.db import connection

from bridgeos_agent.firewall import RobotNetwork, cloud_rules, robot_rules
from network import openvpn, pki, services
from network.models import Authority, ClientCertificate, Revocation
from robots.models import Robot
from robots.rotation import rotate_token
from robots.services import create_robot, delete_robot
from tests.net import netns

NOW = datetime(2026, 1, 1, tzinfo=UTC)


def verify(leaf: x509.Certificate, ca: x509.Certificate) -> None:
    """Raise unless the CA signed the leaf and the leaf is valid now."""
    leaf.verify_directly_issued_by(ca)
    assert leaf.not_valid_before_utc <= NOW <= leaf.not_valid_after_utc


def test_issued_certificates_verify_against_the_ca_and_a_crl_lists_the_revoked():
    ca_key, ca = pki.make_ca("test CA", now=NOW)
    _, server = pki.issue(ca_key, ca, "localhost", server=True, now=NOW, names=["localhost", "10.8.0.1"])
    _, client = pki.issue(ca_key, ca, "robot-1", server=False, now=NOW)
    verify(server, ca)
    verify(client, ca)
    usage = x509.ExtendedKeyUsage
    assert list(server.extensions.get_extension_for_class(usage).value) == [ExtendedKeyUsageOID.SERVER_AUTH]
    assert list(client.extensions.get_extension_for_class(usage).value) == [ExtendedKeyUsageOID.CLIENT_AUTH]
    names = server.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    assert [str(ip) for ip in names.get_values_for_type(x509.IPAddress)] == ["10.8.0.1"]
    crl = pki.make_crl(ca_key, ca, [(client.serial_number, NOW)], now=NOW)
    assert crl.is_signature_valid(ca.public_key())
    assert crl.get_revoked_certificate_by_serial_number(client.serial_number) is not None
    assert crl.get_revoked_certificate_by_serial_number(server.serial_number) is None
    _, other_ca = pki.make_ca("another CA", now=NOW)
    with pytest.raises(ValueError, match="does not match certificate issuer"):
        verify(client, other_ca)


@pytest.mark.django_db
def test_deleting_or_rotating_a_robot_revokes_its_certificate_and_the_crl_says_so():
    owner = get_user_model().objects.create_user("owner")
    robot, _ = create_robot("r1", owner)
    first = services.client_certificate(robot)
    rotate_token(robot)
    assert not ClientCertificate.objects.filter(serial=first.serial).exists()
    second = services.client_certificate(Robot.objects.get(id="r1"))
    assert second.serial != first.serial
    delete_robot(Robot.objects.get(id="r1"))
    assert set(Revocation.objects.values_list("serial", "reason")) == {
        (first.serial, "credentials rotated"),
        (second.serial, "robot deleted"),
    }
    crl = x509.load_pem_x509_crl(services.crl_pem().encode())
    assert {format(entry.serial_number, "x") for entry in crl} == {first.serial, second.serial}


@pytest.mark.django_db
def test_the_server_files_give_each_robot_exactly_its_routes(settings, tmp_path):
    settings.BRIDGEOS_NETWORK = {**settings.BRIDGEOS_NETWORK, "VPN_REMOTES": ["vpn.example:1194"]}
    owner = get_user_model().objects.create_user("owner")
    robot, _ = create_robot("r1", owner)
    local, cloud = robot.config["subnets"]["local"], robot.config["subnets"]["cloud"]
    changed = services.write_files(tmp_path, services.server_files())
    assert {"server.conf", "ccd/r1", "crl.pem", "server.key"} <= set(changed)
    assert services.write_files(tmp_path, services.server_files()) == []  # nothing changed, nothing rewritten
    entry = (tmp_path / "ccd" / "r1").read_text().splitlines()[1:]
    assert entry[1] == f"iroute {local.replace('/24', '')} 255.255.255.0"
    assert entry[2] == f'push "route {cloud.replace("/24", "")} 255.255.255.0"'
    assert oct((tmp_path / "server.key").stat().st_mode & 0o777) == "0o600"
    profile = services.client_profile(Robot.objects.get(id="r1"))
    assert "remote vpn.example 1194" in profile and "BEGIN PRIVATE KEY" in profile
    assert f"verify-x509-name {openvpn.SERVER_NAME} name" in profile
    delete_robot(Robot.objects.get(id="r1"))
    assert "ccd/r1 (removed)" in services.write_files(tmp_path, services.server_files())


def test_openvpn_accepts_the_rendered_server_config(tmp_path):
    if subprocess.run(["which", "openvpn"], capture_output=True).returncode:
        pytest.skip("openvpn is not installed (scripts/services.sh vpn)")
    text = openvpn.server_config(
        device="bosnet-chk",
        proto="udp",
        port=1194,
        vpn_network="10.8.0.0/16",
        server_ip="10.8.0.1",
        local_pools=["10.64.0.0/12"],
    )
    (tmp_path / "server.conf").write_text(text)
    # --verb 0 with an unknown option would fail; --show-... is not enough: parse only, then stop at the files.
    result = subprocess.run(
        ["openvpn", "--cd", str(tmp_path), "--config", "server.conf", "--route-noexec", "--ifconfig-noexec"],
        capture_output=True,
        text=True,
        timeout=30,
    )
    # The keys are missing on purpose: OpenVPN got past parsing every option to the first file it needs.
    assert "Unrecognized option" not in result.stdout + result.stderr
    assert "ca.crt" in result.stdout + result.stderr or "Cannot" in result.stdout + result.stderr


NETWORKS = [
    RobotNetwork("r1", "10.64.0.0/24", "10.80.0.0/24", "10.8.0.2/32"),
    RobotNetwork("r2", "10.64.1.0/24", "10.80.1.0/24"),
]


def test_cloud_rules_pair_each_robot_with_its_own_cloud_subnet_only():
    rules = cloud_rules(NETWORKS, device="bridgeos-vpn", service_ports=[8443])
    assert "10.64.0.0/24 . 10.80.0.0/24" in rules and "10.8.0.2 . 10.80.0.0/24" in rules
    assert "10.64.0.0/24 . 10.80.1.0/24" not in rules
    assert "tcp dport { 8443 } accept" in rules
    with pytest.raises(ValueError, match="IPv4"):
        RobotNetwork("r3", "fd00::/64", "10.80.2.0/24")
    with pytest.raises(ValueError, match="device"):
        cloud_rules(NETWORKS, device='x" ; flush ruleset', service_ports=[8443])


@pytest.mark.skipif(netns.available() is not None, reason=f"nft in a namespace: {netns.available()}")
def test_nft_loads_both_rulesets_and_replaces_them_atomically():
    world = netns.Network()
    try:
        host = world.host("nft")
        rules = [
            cloud_rules(NETWORKS, device="bridgeos-vpn", service_ports=[8443]),
            cloud_rules([], device="bridgeos-vpn", service_ports=[8443]),
            robot_rules(NETWORKS[0], device="bridgeos-vpn", server="10.8.0.1", service_ports=[8443]),
        ]
        for text in rules * 2:  # loading twice replaces the table rather than failing or doubling it
            result = subprocess.run(
                world.command(host, ["nft", "-f", "-"]), input=text, capture_output=True, text=True, timeout=30
            )
            assert result.returncode == 0, result.stderr
        listing = world.exec(host, "nft", "list", "tables").stdout.split("\n")
        assert [line for line in listing if line] == ["table inet bridgeos"]
    finally:
        world.close()


def raw_keys() -> list[str]:
    """Return the key_pem columns as the database holds them."""
    with connection.cursor() as cursor:
        cursor.execute("SELECT key_pem FROM network_authority UNION ALL SELECT key_pem FROM network_clientcertificate")
        return [row[0] for row in cursor.fetchall()]


@pytest.mark.django_db
def test_private_keys_are_sealed_in_the_database_and_open_in_python():
    robot, _ = create_robot("sealed-1", get_user_model().objects.create_user("sealed-owner"))
    cert = services.client_certificate(robot)
    services.authority("tls-crypt")
    stored = raw_keys()
    assert len(stored) >= 3  # the CA, the tls-crypt key and the robot's key at least
    for text in stored:
        assert text.startswith(pki.SEALED)
        assert "PRIVATE KEY" not in text and "OpenVPN Static key" not in text
    # Read back through the model, the key is the one that matches the robot's certificate.
    key = pki.load_key(ClientCertificate.objects.get(robot=robot).key_pem)
    assert key.public_key() == pki.load_cert(cert.cert_pem).public_key()


@pytest.mark.django_db
def test_the_migration_seals_keys_stored_plain_before_it():
    robot, _ = create_robot("sealed-2", get_user_model().objects.create_user("sealed-owner-2"))
    services.client_certificate(robot)
    ca_plain = Authority.objects.get(name="ca").key_pem
    with connection.cursor() as cursor:  # as an older cloud left them
        cursor.execute("UPDATE network_authority SET key_pem = %s WHERE name = 'ca'", [ca_plain])
    assert ca_plain in raw_keys()
    migration = importlib.import_module("network.migrations.0002_sealed_private_keys")
    migration.seal_existing(apps, None)
    assert all(text.startswith(pki.SEALED) and "PRIVATE KEY" not in text for text in raw_keys())
    assert Authority.objects.get(name="ca").key_pem == ca_plain


def test_a_sealed_key_opens_only_with_its_sealing_key():
    sealed = pki.seal("-----BEGIN PRIVATE KEY-----\nx\n", pki.sealing_key("one passphrase"))
    assert pki.unseal(sealed, pki.sealing_key("one passphrase")).startswith("-----BEGIN PRIVATE KEY")
    with pytest.raises(pki.SealError, match="BRIDGEOS_PKI_KEY"):
        pki.unseal(sealed, pki.sealing_key("another"))

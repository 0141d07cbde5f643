"""Domain actions on robots' networks: the config robots get, certificates, revocation, the server's files."""

from __future__ import annotations

import os
import time
from collections.abc import Iterable
from datetime import timedelta
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

from django.conf import settings
from django.db import connection, transaction
from django.utils import timezone

from bridgeos_agent.firewall import RobotNetwork, cloud_rules
from monitoring.choices import Level
from monitoring.services import record_event
from robots.models import Robot

from . import ipam, openvpn, pki
from .models import Authority, ClientCertificate, Revocation, Subnet

# pg_advisory_xact_lock key of the PKI ("bosp").
PKI_LOCK = 0x626F_7370
CLIENT_DAYS = 825


class VpnUnavailable(Exception):
    """The cloud offers no VPN (BRIDGEOS_VPN_REMOTE is unset)."""


def _conf() -> dict[str, Any]:
    return settings.BRIDGEOS_NETWORK


def _lock(key: int) -> None:
    if connection.vendor == "postgresql":
        with connection.cursor() as cursor:
            cursor.execute("SELECT pg_advisory_xact_lock(%s)", [key])


# --------------------------------------------------------------------------- the robot config


def sync_robot_config(robot: Robot) -> dict[str, Any]:
    """Allocate the robot's subnets and put them, the VPN's address and the pinned CA in its config."""
    with transaction.atomic():
        allocated = ipam.ensure_subnets(robot)
        config = dict(robot.config)
        config["subnets"] = {"local": allocated["local"], "cloud": allocated["cloud"]}
        if _conf()["VPN_REMOTES"]:
            config["vpn"] = {**(config.get("vpn") or {}), "master": _conf()["VPN_MASTER"]}
        if _conf()["PIN_CA"]:
            config["tls_ca"] = authority("ca").cert_pem
        if config != robot.config:
            Robot.objects.filter(pk=robot.pk).update(config=config)
            robot.config = config
    return config


# --------------------------------------------------------------------------- the PKI


def authority(name: str) -> Authority:
    """Return one of the cloud's keys, creating the CA and the server certificates the first time."""
    found = Authority.objects.filter(name=name).first()
    if found is not None:
        return found
    with transaction.atomic():
        _lock(PKI_LOCK)
        found = Authority.objects.filter(name=name).first()
        if found is not None:
            return found
        now = timezone.now()
        if name == "ca":
            key, cert = pki.make_ca("bridgeOS cloud CA", now=now)
            made = Authority(name=name, cert_pem=pki.pem(cert), key_pem=pki.key_pem(key))
        elif name == "tls-crypt":
            made = Authority(name=name, key_pem=pki.tls_crypt_key())
        elif name in ("vpn-server", "tls-server"):
            ca = authority("ca")
            if name == "vpn-server":
                common, names = openvpn.SERVER_NAME, []
            else:
                names = list(dict.fromkeys([*_conf()["TLS_NAMES"], _conf()["VPN_SERVER_IP"]]))
                common = names[0]
            key, cert = pki.issue(
                pki.load_key(ca.key_pem), pki.load_cert(ca.cert_pem), common, server=True, now=now, names=names
            )
            made = Authority(name=name, cert_pem=pki.pem(cert), key_pem=pki.key_pem(key))
        else:
            raise ValueError(f"unknown authority {name!r}")
        made.save()
        record_event(f"PKI: {name} created", kind="pki_created", data={"name": name})
        return made


def client_certificate(robot: Robot) -> ClientCertificate:
    """Return the robot's VPN certificate, issuing one if it has none (first use, or after a rotation)."""
    with transaction.atomic():
        Robot.objects.select_for_update().filter(pk=robot.pk).first()
        existing = ClientCertificate.objects.filter(robot=robot).first()
        if existing is not None:
            return existing
        ca = authority("ca")
        key, cert = pki.issue(
            pki.load_key(ca.key_pem),
            pki.load_cert(ca.cert_pem),
            robot.id,
            server=False,
            now=timezone.now(),
            days=CLIENT_DAYS,
        )
        issued = ClientCertificate.objects.create(
            robot=robot,
            serial=format(cert.serial_number, "x"),
            cert_pem=pki.pem(cert),
            key_pem=pki.key_pem(key),
            not_after=cert.not_valid_after_utc,
        )
        record_event(
            f"VPN certificate issued to robot {robot.id}",
            robot_id=robot.id,
            kind="vpn_certificate_issued",
            data={"serial": issued.serial},
        )
        return issued


def revoke_certificate(robot: Robot, reason: str) -> Revocation | None:
    """Revoke the robot's VPN certificate (it joins the CRL); the next profile carries a new one."""
    with transaction.atomic():
        cert = ClientCertificate.objects.select_for_update().filter(robot_id=robot.pk).first()
        if cert is None:
            return None
        revocation = Revocation.objects.create(
            serial=cert.serial, robot_id=robot.pk, reason=reason[:200], not_after=cert.not_after
        )
        cert.delete()
        record_event(
            f"VPN certificate of robot {robot.pk} revoked: {reason}",
            robot_id=robot.pk if Robot.objects.filter(pk=robot.pk).exists() else None,
            level=Level.WARNING,
            kind="vpn_certificate_revoked",
            data={"robot": robot.pk, "serial": cert.serial, "reason": reason},
        )
        return revocation


_crls: dict[tuple[str, tuple[str, ...]], tuple[str, float]] = {}
CRL_REFRESH_S = 7 * 24 * 3600.0  # well inside its 30 days of validity


def crl_pem() -> str:
    """Return the CRL of every revoked certificate that has not expired yet, re-signed only when it changes."""
    ca = authority("ca")
    now = timezone.now()
    revoked = list(
        Revocation.objects.filter(not_after__gt=now - timedelta(days=1))
        .order_by("serial")
        .values_list("serial", "revoked_at")
    )
    key = (ca.cert_pem, tuple(serial for serial, _ in revoked))
    cached = _crls.get(key)
    if cached is not None and time.monotonic() - cached[1] < CRL_REFRESH_S:
        return cached[0]
    crl = pki.make_crl(
        pki.load_key(ca.key_pem), pki.load_cert(ca.cert_pem), ((int(s, 16), at) for s, at in revoked), now=now
    )
    _crls.clear()
    _crls[key] = (pki.pem(crl), time.monotonic())
    return _crls[key][0]


def client_profile(robot: Robot) -> str:
    """Return the robot's OpenVPN profile, with its certificate and key."""
    if not _conf()["VPN_REMOTES"]:
        raise VpnUnavailable("this cloud offers no VPN: set BRIDGEOS_VPN_REMOTE to host:port")
    sync_robot_config(robot)
    cert = client_certificate(robot)
    return openvpn.client_profile(
        robot=robot.id,
        remotes=_conf()["VPN_REMOTES"],
        proto=_conf()["VPN_PROTO"],
        ca_pem=authority("ca").cert_pem,
        cert_pem=cert.cert_pem,
        key_pem=cert.key_pem,
        tls_crypt=authority("tls-crypt").key_pem,
        device=_conf()["VPN_DEVICE"],
    )


# --------------------------------------------------------------------------- the server side


def robot_networks() -> list[RobotNetwork]:
    """Return every robot's local, cloud and tunnel networks."""
    by_robot: dict[str, dict[str, str]] = {}
    for robot_id, kind, network in Subnet.objects.values_list("robot_id", "kind", "network"):
        by_robot.setdefault(robot_id, {})[kind] = network
    return [
        RobotNetwork(robot_id, nets["local"], nets["cloud"], nets.get("tunnel"))
        for robot_id, nets in sorted(by_robot.items())
        if "local" in nets and "cloud" in nets
    ]


def firewall_rules() -> str:
    """Return the cloud's nftables rules for every robot."""
    master = urlsplit(_conf()["VPN_MASTER"])
    port = master.port or (443 if master.scheme == "wss" else 80)
    return cloud_rules(robot_networks(), device=_conf()["VPN_DEVICE"], service_ports=[port])


def server_files() -> dict[str, tuple[str, int]]:
    """Return every file of the OpenVPN server's directory: relative path -> (content, mode)."""
    conf = _conf()
    server = authority("vpn-server")
    files = {
        "server.conf": (
            openvpn.server_config(
                device=conf["VPN_DEVICE"],
                proto=conf["VPN_PROTO"],
                port=conf["VPN_PORT"],
                vpn_network=conf["VPN_NETWORK"],
                server_ip=conf["VPN_SERVER_IP"],
                local_pools=conf["LOCAL_POOLS"],
            ),
            0o644,
        ),
        "ca.crt": (authority("ca").cert_pem, 0o644),
        "server.crt": (server.cert_pem, 0o644),
        "server.key": (server.key_pem, 0o600),
        "tls-crypt.key": (authority("tls-crypt").key_pem, 0o600),
        "crl.pem": (crl_pem(), 0o644),
    }
    for network in robot_networks():
        if network.tunnel is None:
            continue
        entry = openvpn.ccd_entry(
            robot=network.robot,
            tunnel=network.tunnel,
            vpn_network=conf["VPN_NETWORK"],
            local=network.local,
            cloud=network.cloud,
        )
        files[f"ccd/{network.robot}"] = (entry, 0o644)
    return files


def write_files(directory: Path, files: dict[str, tuple[str, int]]) -> list[str]:
    """Write the files whose content changed (atomically) and remove stale ccd entries; return what changed."""
    directory.mkdir(parents=True, exist_ok=True)
    (directory / "ccd").mkdir(exist_ok=True)
    changed = []
    for name, (content, mode) in files.items():
        path = directory / name
        try:
            if path.read_text() == content:
                continue
        except OSError:
            pass
        tmp = path.with_name(f".{path.name}.tmp")
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, mode)
        with os.fdopen(fd, "w") as out:
            out.write(content)
        os.chmod(tmp, mode)
        os.replace(tmp, path)
        changed.append(name)
    for stale in (directory / "ccd").iterdir():
        if f"ccd/{stale.name}" not in files:
            stale.unlink()
            changed.append(f"ccd/{stale.name} (removed)")
    return changed


def revoked_robots_since(serials: Iterable[str]) -> tuple[set[str], set[str]]:
    """Return (all revoked serials, robots whose certificates were revoked and are not in ``serials``)."""
    known = set(serials)
    rows = list(Revocation.objects.values_list("serial", "robot_id"))
    return {serial for serial, _ in rows}, {robot for serial, robot in rows if serial not in known}

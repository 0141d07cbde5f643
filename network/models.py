"""Robots' subnets, the cloud's certificate authority and the robots' VPN certificates."""

from __future__ import annotations

import functools
import ipaddress
from typing import Any

from cryptography.fernet import Fernet
from django.conf import settings
from django.db import models
from django.utils import timezone

from robots.models import Robot

from . import pki


class CidrField(models.CharField):
    """A network in CIDR notation: PostgreSQL's cidr type (so overlaps can be constrained), text elsewhere."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        kwargs.setdefault("max_length", 43)
        super().__init__(*args, **kwargs)

    def db_type(self, connection: Any) -> str:
        return "cidr" if connection.vendor == "postgresql" else super().db_type(connection)

    def from_db_value(self, value: Any, expression: Any, connection: Any) -> str | None:
        return None if value is None else str(value)

    def get_prep_value(self, value: Any) -> str | None:
        return None if value is None else str(ipaddress.ip_network(value, strict=True))


@functools.cache
def _sealing_key(secret: str) -> Fernet:
    return pki.sealing_key(secret)


class SealedTextField(models.TextField):
    """A secret (a private key) encrypted at rest with BRIDGEOS_PKI_KEY; plain text in Python."""

    def from_db_value(self, value: Any, expression: Any, connection: Any) -> str | None:
        return None if value is None else pki.unseal(value, _sealing_key(settings.BRIDGEOS_PKI_KEY))

    def get_prep_value(self, value: Any) -> str | None:
        value = super().get_prep_value(value)
        return None if value is None else pki.seal(value, _sealing_key(settings.BRIDGEOS_PKI_KEY))


class Subnet(models.Model):
    """A network allocated to one robot; no two allocations overlap (an exclusion constraint on PostgreSQL)."""

    class Kind(models.TextChoices):
        LOCAL = "local", "local (the robot's container network)"
        CLOUD = "cloud", "cloud (the robot's cloud container network)"
        TUNNEL = "tunnel", "tunnel (the robot's VPN address)"

    robot = models.ForeignKey(Robot, on_delete=models.CASCADE, related_name="subnets")
    kind = models.CharField(max_length=8, choices=Kind.choices)
    network = CidrField(unique=True)
    created_at = models.DateTimeField(default=timezone.now, editable=False)

    class Meta:
        ordering = ["robot_id", "kind"]
        constraints = [models.UniqueConstraint(fields=["robot", "kind"], name="subnet_one_per_kind")]
        # PostgreSQL also gets EXCLUDE USING gist (network inet_ops WITH &&): see migration 0001.

    def __str__(self) -> str:
        return f"{self.robot_id} {self.kind} {self.network}"


class Authority(models.Model):
    """One of the cloud's own keys: the CA, the VPN server, the TLS server, the tls-crypt key."""

    name = models.CharField(max_length=32, unique=True)
    cert_pem = models.TextField(blank=True)
    key_pem = SealedTextField()
    created_at = models.DateTimeField(default=timezone.now, editable=False)

    class Meta:
        verbose_name_plural = "authorities"

    def __str__(self) -> str:
        return self.name


class ClientCertificate(models.Model):
    """The VPN certificate a robot holds now (its private key is served only to the robot and its owner)."""

    robot = models.OneToOneField(Robot, on_delete=models.CASCADE, related_name="vpn_certificate")
    serial = models.CharField(max_length=64, unique=True)
    cert_pem = models.TextField()
    key_pem = SealedTextField()
    not_after = models.DateTimeField()
    created_at = models.DateTimeField(default=timezone.now, editable=False)

    def __str__(self) -> str:
        return f"VPN certificate {self.serial[:12]}… of {self.robot_id}"


class Revocation(models.Model):
    """A revoked certificate, kept (without a foreign key) after its robot is gone, for the CRL."""

    serial = models.CharField(max_length=64, unique=True)
    robot_id = models.CharField(max_length=64)
    reason = models.CharField(max_length=200)
    not_after = models.DateTimeField(help_text="Listed in the CRL until the certificate expires.")
    revoked_at = models.DateTimeField(default=timezone.now)

    class Meta:
        ordering = ["revoked_at"]

    def __str__(self) -> str:
        return f"{self.serial[:12]}… of {self.robot_id} revoked: {self.reason}"

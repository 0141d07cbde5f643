"""Private robot networks: subnets (IPAM), the VPN's PKI and OpenVPN config, firewall rules."""

from __future__ import annotations

from django.apps import AppConfig


class NetworkConfig(AppConfig):
    name = "network"
    verbose_name = "Robot networks and VPN"

    def ready(self) -> None:
        from . import signals  # noqa: F401 - connects the receivers

"""App config of the registry: the cloud as the token server of CNCF Distribution registries."""

from __future__ import annotations

from django.apps import AppConfig


class RegistryConfig(AppConfig):
    """Register the registry app."""

    name = "registry"
    verbose_name = "Container registry"

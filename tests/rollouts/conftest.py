"""The registry tests' real registry and tiny image (pinning a release's images), and the agent tests' cloud."""

from __future__ import annotations

from tests.agent.conftest import cloud
from tests.registry.conftest import registry, tiny_image

__all__ = ["cloud", "registry", "tiny_image"]

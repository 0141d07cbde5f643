"""Read Docker image references: which registry, which repository, which tag or digest."""

from __future__ import annotations

__all__ = ["split_reference"]


def split_reference(image: str) -> tuple[str | None, str, str]:
    """Split an image reference into (registry or None, repository, tag or digest), as Docker reads it."""
    name, _, digest = image.partition("@")
    first, slash, rest = name.partition("/")
    registry = first if slash and ("." in first or ":" in first or first == "localhost") else None
    path, tag = (rest if registry else name), ""
    if ":" in path.rsplit("/", 1)[-1]:
        path, _, tag = path.rpartition(":")
    return registry, path, digest or tag or "latest"

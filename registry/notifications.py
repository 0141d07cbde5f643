"""Read a Distribution registry's notification envelope: the tags its clients pushed (pure functions)."""

from __future__ import annotations

from dataclasses import dataclass
from datetime import UTC, datetime
from typing import Any

__all__ = ["MANIFEST_TYPES", "TagPush", "tag_pushes"]

MANIFEST_TYPES = frozenset(
    {
        "application/vnd.docker.distribution.manifest.v2+json",
        "application/vnd.docker.distribution.manifest.list.v2+json",
        "application/vnd.oci.image.manifest.v1+json",
        "application/vnd.oci.image.index.v1+json",
    }
)


@dataclass(frozen=True)
class TagPush:
    """One tag pushed: which repository, which tag, the manifest it now names, by whom and when."""

    repository: str
    tag: str
    digest: str
    media_type: str
    size: int
    actor: str
    at: datetime


def tag_pushes(envelope: Any) -> list[TagPush]:
    """Return the manifest pushes with a tag in an envelope; anything else (blobs, pulls, junk) is skipped."""
    events = envelope.get("events") if isinstance(envelope, dict) else None
    found = []
    for event in events if isinstance(events, list) else []:
        if not isinstance(event, dict) or event.get("action") != "push":
            continue
        target = event.get("target") if isinstance(event.get("target"), dict) else {}
        repository, tag, digest = target.get("repository"), target.get("tag"), target.get("digest")
        media_type = target.get("mediaType", "")
        if media_type not in MANIFEST_TYPES or not all(isinstance(v, str) and v for v in (repository, tag, digest)):
            continue
        if len(repository) > 255 or len(tag) > 128 or not digest.startswith("sha256:") or len(digest) > 80:
            continue
        actor = event.get("actor") if isinstance(event.get("actor"), dict) else {}
        found.append(
            TagPush(
                repository=repository,
                tag=tag,
                digest=digest,
                media_type=media_type,
                size=int(target.get("size") or target.get("length") or 0),
                actor=str(actor.get("name") or "")[:150],
                at=_timestamp(event.get("timestamp")),
            )
        )
    return found


def _timestamp(text: Any) -> datetime:
    """Read the event's RFC 3339 time (nanoseconds cut to microseconds); now when it has none."""
    if isinstance(text, str):
        head, dot, rest = text.partition(".")
        if dot:
            digits = "".join(c for c in rest if c.isdigit())
            zone = rest[len(digits) :]
            text = f"{head}.{digits[:6]}{zone}"
        try:
            return datetime.fromisoformat(text.replace("Z", "+00:00"))
        except ValueError:
            pass
    return datetime.now(UTC)

"""Domain actions on releases: make the next one of a Skill, validated and pinned; tell who may see which."""

from __future__ import annotations

import re
from typing import Any

from django.contrib.auth.models import AbstractBaseUser
from django.core.exceptions import ValidationError
from django.db import connection, transaction
from django.db.models import Max, QuerySet

from bridgeos_agent.skillconfig import parse_skill_config
from bridgeos_cloud.errors import NotFound
from bridgeos_cloud.validation import validated_config
from registry.pinning import pin_images
from robots.access import Actor
from teams.models import Organization

from .models import Release

DIGEST = re.compile(r"@sha256:[0-9a-f]{64}$")


def unpinned_images(config: dict[str, Any]) -> list[str]:
    """Name each launch spec image of a Skill config that is not pinned by a sha256 digest."""
    return [
        f"components.{component_id}.{where}.image: {image!r} is not pinned by digest (push it to the cloud's "
        "registry, or name it as image@sha256:<digest>)"
        for component_id, component in config.get("components", {}).items()
        for where in ("robot", "cloud")
        if (image := (component.get(where) or {}).get("image")) and not DIGEST.search(image)
    ]


def release_config(config: Any, organization: Organization) -> dict[str, Any]:
    """Return a config validated as a Skill add does, with every image pinned; ValidationError naming what is not."""
    if not isinstance(config, dict):
        raise ValidationError({"config": ["A Skill config is a JSON object."]})
    pinned = pin_images(validated_config(parse_skill_config, config), organization)
    problems = unpinned_images(pinned)
    if problems:
        raise ValidationError({"config": problems}, code="unpinned_image")
    return pinned


def create_release(
    organization: Organization,
    config: Any,
    *,
    name: str = "",
    notes: str = "",
    user: AbstractBaseUser | None = None,
) -> Release:
    """Make the next numbered release of a Skill in an organization, all or nothing."""
    # Outside the transaction: asking the registry for digests can take a while.
    pinned = release_config(config, organization)
    skill_id = pinned["skill_id"]
    with transaction.atomic():
        _lock_numbering(organization.id, skill_id)
        last = Release.objects.filter(organization=organization, skill_id=skill_id).aggregate(last=Max("number"))
        return Release.objects.create(
            organization=organization,
            skill_id=skill_id,
            number=(last["last"] or 0) + 1,
            name=name,
            notes=notes,
            config=pinned,
            created_by=user,
            created_by_name=user.get_username() if user is not None else "",
        )


def _lock_numbering(organization_id: int, skill_id: str) -> None:
    """Hold the numbering of one Skill's releases until the transaction ends, so two creates never share a number."""
    if connection.vendor != "postgresql":
        return  # the unique constraint still refuses a shared number
    with connection.cursor() as cursor:
        cursor.execute(
            "SELECT pg_advisory_xact_lock(hashtextextended(%s, 0))", [f"rollouts.release/{organization_id}/{skill_id}"]
        )


def release_organization(actor: Actor, slug: str | None) -> Organization:
    """Return the organization a new release goes to: the one named, else the request's scope, else the only one.

    A named organization the request does not reach is as unknown as a missing one: NotFound for both.
    """
    if slug is not None:
        ids = actor.organization_ids()
        found = Organization.objects.filter(slug=slug)
        organization = (found if ids is None else found.filter(id__in=ids)).first()
        if organization is None:
            raise NotFound("No such organization of yours.", field="organization")
        return organization
    if actor.organization_id is not None:
        return Organization.objects.get(id=actor.organization_id)
    ids = list(actor.roles())
    if len(ids) != 1:
        raise ValidationError({"organization": ["Name the organization (its slug) the release belongs to."]})
    return Organization.objects.get(id=ids[0])


def visible_releases(actor: Actor) -> QuerySet[Release]:
    """Return the releases of the organizations a request reaches (staff: all)."""
    ids = actor.organization_ids()
    releases = Release.objects.select_related("organization")
    return releases if ids is None else releases.filter(organization_id__in=ids)

"""The registry's actions: the signing key, who a credential is, the token it earns, and the tags pushed."""

from __future__ import annotations

import functools
import hashlib
import hmac
from datetime import UTC, datetime
from typing import Any

from cryptography.hazmat.primitives.asymmetric import ec
from django.conf import settings
from django.db import transaction

from audit import services as audit
from bridgeos_cloud.env import ConfigError, kept_secret
from network import pki
from robots.access import Who, as_actor
from robots.models import Robot
from teams.models import Organization
from teams.roles import Role

from . import notifications, tokens
from .models import RegistryTag

# More scopes than any client sends (docker asks for one or two): a bound on the work one request causes.
MAX_SCOPES = 50


@functools.cache
def signing_key() -> ec.EllipticCurvePrivateKey:
    """Return the key that signs registry tokens: BRIDGEOS_REGISTRY_KEY(_FILE), else one kept in DATA_DIR."""
    configured = settings.BRIDGEOS["REGISTRY_KEY"]
    path = settings.DATA_DIR / "registry_key.pem"
    text = configured or kept_secret(path, lambda: pki.key_pem(pki.new_key()).encode())
    try:
        return pki.load_key(text)
    except (ValueError, TypeError, AssertionError):
        where = "BRIDGEOS_REGISTRY_KEY" if configured else str(path)
        raise ConfigError(f"{where} is not an unencrypted PEM EC private key (P-256) to sign registry tokens") from None


def principal_of(who: Who, robot: Robot | None = None) -> tokens.Principal:
    """Describe a request's user with their roles in each organization, or a robot, for the grant rules.

    A robot pulls from its own organization's namespace and nowhere else (staff's robots too).
    """
    if robot is not None:
        return robot_principal(robot)
    actor = as_actor(who)
    user = actor.user
    slugs = dict(Organization.objects.filter(id__in=actor.roles()).values_list("id", "slug"))
    namespaces = tuple((slugs[org], role) for org in slugs if (role := actor.role_in(org)) is not None)
    return tokens.Principal(
        username=user.get_username(),
        is_staff=actor.everywhere,
        is_active=bool(user.is_active),
        namespaces=namespaces,
    )


def robot_principal(robot: Robot) -> tokens.Principal:
    """Describe a robot, or a cloud copy of its Skill, pulling its organization's images."""
    slug = Organization.objects.values_list("slug", flat=True).get(id=robot.organization_id)
    return tokens.Principal(username=slug, robot=robot.id, namespaces=((slug, str(Role.VIEWER)),))


def organization_principal(organization: Organization) -> tokens.Principal:
    """Describe an organization pulling its own images as its robots do (a release is pinned by what they may pull)."""
    return tokens.Principal(username=organization.slug, namespaces=((organization.slug, str(Role.VIEWER)),))


def parse_scopes(texts: list[str]) -> list[tokens.Scope]:
    """Parse the request's scope parameters (each may list several, space-separated); raise ScopeError."""
    parts = [part for text in texts for part in text.split(" ") if part]
    if len(parts) > MAX_SCOPES:
        raise tokens.ScopeError(f"{len(parts)} scopes asked for; at most {MAX_SCOPES} per request")
    return [tokens.parse_scope(part) for part in parts]


def issue_token(who: Who, scope_texts: list[str], *, robot: Robot | None = None, service: str = "") -> dict[str, Any]:
    """Return Distribution's token answer for the scopes asked; raise ScopeError for a malformed one.

    No refresh_token: docker would redeem it with a POST this realm does not serve.
    """
    scopes = parse_scopes(scope_texts)
    principal = principal_of(who, robot)
    conf = settings.BRIDGEOS
    now = datetime.now(UTC)
    claims = tokens.token_claims(
        principal,
        scopes,
        issuer=conf["REGISTRY_ISSUER"],
        audience=service or conf["REGISTRY_SERVICE"],
        now=now,
        ttl_s=conf["REGISTRY_TOKEN_TTL_S"],
    )
    token = tokens.sign(claims, signing_key())
    issued_at = datetime.fromtimestamp(claims["iat"], UTC).isoformat().replace("+00:00", "Z")
    return {"token": token, "access_token": token, "expires_in": claims["exp"] - claims["iat"], "issued_at": issued_at}


def notify_token() -> str:
    """Return what the registry presents when it tells the cloud of a push (derived from SECRET_KEY)."""
    return hmac.new(settings.SECRET_KEY.encode(), b"bridgeos registry notifications", hashlib.sha256).hexdigest()


def record_pushes(pushes: list[notifications.TagPush]) -> int:
    """Point each pushed tag at its new manifest; return how many tags were written."""
    with transaction.atomic():
        for push in pushes:
            RegistryTag.objects.update_or_create(
                repository=push.repository,
                tag=push.tag,
                defaults={
                    "namespace": push.repository.partition("/")[0],
                    "digest": push.digest,
                    "media_type": push.media_type,
                    "size": push.size,
                    "pushed_by": push.actor,
                    "pushed_at": push.at,
                },
            )
            # After the commit: an entry only for a push that stuck, and never the chain's lock while tags are locked.
            transaction.on_commit(
                functools.partial(audit.record_registry_push, push.repository, push.tag, push.digest, push.actor)
            )
    return len(pushes)


def repositories(who: Who, namespace: str | None = None) -> list[dict[str, Any]]:
    """List the repositories a request may pull, with their tags and digests (staff: every namespace)."""
    tags = RegistryTag.objects.all()
    principal = principal_of(who)
    if not principal.is_staff:
        tags = tags.filter(namespace__in=[slug for slug, _ in principal.namespaces or ()])
    if namespace:
        tags = tags.filter(namespace=namespace)
    listed: dict[str, dict[str, Any]] = {}
    for tag in tags.order_by("repository", "tag"):
        entry = listed.setdefault(
            tag.repository, {"repository": tag.repository, "namespace": tag.namespace, "tags": []}
        )
        entry["tags"].append(
            {
                "tag": tag.tag,
                "digest": tag.digest,
                "size": tag.size,
                "pushed_by": tag.pushed_by,
                "pushed_at": tag.pushed_at.isoformat(),
            }
        )
    return list(listed.values())

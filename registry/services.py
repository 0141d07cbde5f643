"""The registry's actions: the signing key, who a credential is, the token it earns, and the tags pushed."""

from __future__ import annotations

import functools
import hashlib
import hmac
from datetime import UTC, datetime
from typing import Any

from cryptography.hazmat.primitives.asymmetric import ec
from django.conf import settings
from django.contrib.auth.models import AbstractBaseUser
from django.db import transaction

from bridgeos_cloud.env import ConfigError, kept_secret
from network import pki
from robots.models import Robot

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


def principal_of(user: AbstractBaseUser, robot: Robot | None = None) -> tokens.Principal:
    """Describe a user, or a robot acting with its owner's rights, for the grant rules."""
    return tokens.Principal(
        username=user.get_username(),
        is_staff=bool(user.is_staff),
        is_active=bool(user.is_active),
        robot=robot.id if robot is not None else None,
    )


def parse_scopes(texts: list[str]) -> list[tokens.Scope]:
    """Parse the request's scope parameters (each may list several, space-separated); raise ScopeError."""
    parts = [part for text in texts for part in text.split(" ") if part]
    if len(parts) > MAX_SCOPES:
        raise tokens.ScopeError(f"{len(parts)} scopes asked for; at most {MAX_SCOPES} per request")
    return [tokens.parse_scope(part) for part in parts]


def issue_token(
    user: AbstractBaseUser, scope_texts: list[str], *, robot: Robot | None = None, service: str = ""
) -> dict[str, Any]:
    """Return Distribution's token answer for the scopes asked; raise ScopeError for a malformed one.

    No refresh_token: docker would redeem it with a POST this realm does not serve.
    """
    scopes = parse_scopes(scope_texts)
    principal = principal_of(user, robot)
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
    return len(pushes)


def repositories(user: AbstractBaseUser, namespace: str | None = None) -> list[dict[str, Any]]:
    """List the repositories a user may pull, with their tags and digests (staff: every namespace)."""
    tags = RegistryTag.objects.all()
    if not user.is_staff:
        tags = tags.filter(namespace=user.get_username())
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

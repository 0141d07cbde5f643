"""Distribution's token authentication as pure functions: scopes, grants, the JWT's claims and key id."""

from __future__ import annotations

import base64
import hashlib
import re
import secrets
from collections.abc import Iterable
from dataclasses import dataclass
from datetime import datetime, timedelta
from typing import Any

import jwt
from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import NameOID

__all__ = [
    "Principal",
    "Scope",
    "ScopeError",
    "access_claim",
    "granted",
    "key_id",
    "parse_scope",
    "sign",
    "signing_certificate",
    "token_claims",
]

# Distribution's reference grammar for a repository name: lowercase path components joined by "/".
_COMPONENT = r"[a-z0-9]+(?:(?:[._]|__|-+)[a-z0-9]+)*"
REPOSITORY_NAME = re.compile(rf"^{_COMPONENT}(?:/{_COMPONENT})*$")
_TYPE = re.compile(r"^[a-z0-9]+(?:\([a-z0-9]+\))?$")
_ACTION = re.compile(r"^(?:[a-z]+|\*)$")
MAX_NAME = 255
OWNER_ACTIONS = frozenset({"pull", "push"})
READER_ACTIONS = frozenset({"pull"})
# Members push to their organization's namespace from the developer role up; every member pulls.
PUSHING_ROLES = frozenset({"developer", "admin"})
STAFF_ACTIONS = frozenset({"pull", "push", "delete"})
ROBOT_ACTIONS = frozenset({"pull"})


class ScopeError(ValueError):
    """A scope parameter does not follow `type[(class)]:name:action[,action...]`."""


@dataclass(frozen=True)
class Scope:
    """One requested resource and the actions wanted on it."""

    type: str
    name: str
    actions: tuple[str, ...]


@dataclass(frozen=True)
class Principal:
    """Who asks for a token: a user, or a robot acting for its organization (``robot`` is its id).

    ``namespaces`` maps each namespace (an organization's slug) to the principal's role there;
    None stands for a user in their personal namespace alone, named as they are.
    """

    username: str
    is_staff: bool = False
    is_active: bool = True
    robot: str | None = None
    namespaces: tuple[tuple[str, str], ...] | None = None

    def role_in(self, namespace: str) -> str | None:
        """Return the principal's role in a namespace, or None."""
        if self.namespaces is None:
            return "admin" if namespace == self.username else None
        return dict(self.namespaces).get(namespace)

    @property
    def subject(self) -> str:
        """Name the principal in the token's `sub`; robots are told apart from users of the same name."""
        return f"robot:{self.robot}" if self.robot else self.username


def parse_scope(text: str) -> Scope:
    """Parse one scope; the name may hold colons (a host:port), the type and actions never do."""
    kind, sep, rest = text.partition(":")
    name, sep2, actions_text = rest.rpartition(":")
    if not sep or not sep2 or not kind or not name or not actions_text:
        raise ScopeError(f"scope {text[:100]!r} is not type:name:actions (e.g. repository:alice/hello:pull,push)")
    if not _TYPE.match(kind):
        raise ScopeError(f"scope {text[:100]!r}: the resource type {kind[:40]!r} is not lowercase letters and digits")
    actions = tuple(dict.fromkeys(actions_text.split(",")))
    if not all(_ACTION.match(action) for action in actions):
        raise ScopeError(f"scope {text[:100]!r}: actions are comma-separated lowercase words or '*'")
    if len(name) > MAX_NAME:
        raise ScopeError(f"scope {text[:100]!r}...: the name is longer than {MAX_NAME} characters")
    if kind == "repository" and not REPOSITORY_NAME.match(name):
        raise ScopeError(f"scope {text[:100]!r}: {name[:100]!r} is not a repository name (lowercase a-z 0-9 . _ - /)")
    return Scope(kind, name, actions)


def granted(principal: Principal, scope: Scope) -> tuple[str, ...]:
    """Return the actions of a scope the principal may take, in the order asked; unknown scopes get none."""
    if not principal.is_active:
        return ()
    if scope.type == "registry" and scope.name == "catalog":
        # Listing every repository is an operator's act: a robot never lists, even its staff owner's.
        allowed = frozenset({"*"}) if principal.is_staff and not principal.robot else frozenset()
    elif scope.type == "repository":
        namespace, _, rest = scope.name.partition("/")
        role = principal.role_in(namespace) if rest else None
        if principal.is_staff:
            allowed = STAFF_ACTIONS
        elif role is not None:
            allowed = OWNER_ACTIONS if role in PUSHING_ROLES else READER_ACTIONS
        else:
            allowed = frozenset()
        if principal.robot:
            allowed = allowed & ROBOT_ACTIONS
    else:
        allowed = frozenset()
    return tuple(action for action in scope.actions if action in allowed)


def access_claim(principal: Principal, scopes: Iterable[Scope]) -> list[dict[str, Any]]:
    """Return the `access` claim: what was granted of each resource asked for; nothing granted, no entry."""
    merged: dict[tuple[str, str], list[str]] = {}
    for scope in scopes:
        actions = merged.setdefault((scope.type, scope.name), [])
        actions.extend(action for action in granted(principal, scope) if action not in actions)
    return [{"type": kind, "name": name, "actions": actions} for (kind, name), actions in merged.items() if actions]


def key_id(public_key: ec.EllipticCurvePublicKey) -> str:
    """Return libtrust's key id: SHA-256 of the DER SubjectPublicKeyInfo, first 240 bits, base32, 12 groups of 4."""
    der = public_key.public_bytes(serialization.Encoding.DER, serialization.PublicFormat.SubjectPublicKeyInfo)
    encoded = base64.b32encode(hashlib.sha256(der).digest()[:30]).decode()
    return ":".join(encoded[i : i + 4] for i in range(0, len(encoded), 4))


def token_claims(
    principal: Principal, scopes: Iterable[Scope], *, issuer: str, audience: str, now: datetime, ttl_s: float
) -> dict[str, Any]:
    """Return the JWT claims Distribution checks: one string `aud` (it refuses an array), `exp`, the access."""
    issued = int(now.timestamp())
    return {
        "iss": issuer,
        "sub": principal.subject,
        "aud": audience,
        "exp": issued + int(ttl_s),
        "nbf": issued,
        "iat": issued,
        "jti": secrets.token_urlsafe(16),
        "access": access_claim(principal, scopes),
    }


def sign(claims: dict[str, Any], key: ec.EllipticCurvePrivateKey) -> str:
    """Sign claims as an ES256 JWT whose `kid` names the key the way the registry indexes its trusted keys."""
    return jwt.encode(claims, key, algorithm="ES256", headers={"kid": key_id(key.public_key())})


def signing_certificate(
    key: ec.EllipticCurvePrivateKey, *, common_name: str, now: datetime, days: int = 3650
) -> x509.Certificate:
    """Make the self-signed certificate that carries the public key to a registry's `rootcertbundle`."""
    name = x509.Name(
        [
            x509.NameAttribute(NameOID.ORGANIZATION_NAME, "bridgeOS"),
            x509.NameAttribute(NameOID.COMMON_NAME, common_name),
        ]
    )
    return (
        x509.CertificateBuilder()
        .subject_name(name)
        .issuer_name(name)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - timedelta(minutes=5))
        .not_valid_after(now + timedelta(days=days))
        .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
        .add_extension(
            x509.KeyUsage(True, False, False, False, False, False, False, False, False), critical=True
        )  # digitalSignature
        .sign(key, hashes.SHA256())
    )

"""Write audit entries to the chain, walk it to verify it, and cut it by age."""

from __future__ import annotations

import logging
from collections.abc import Iterator
from dataclasses import dataclass
from datetime import timedelta
from typing import Any

from django.conf import settings
from django.db import connection, transaction
from django.utils import timezone

from .choices import Door, Outcome, outcome_of
from .models import CHAINED, GENESIS, AuditAnchor, AuditEntry

log = logging.getLogger(__name__)

# One lock for every writer (daphne processes, Celery workers), so the chain stays a single line.
CHAIN_LOCK = 0x61756469745F6C  # "audit_l"
DATA_VALUE_CHARS = 300


def _clean(value: str, limit: int) -> str:
    """Cut a string to a field's length and drop NUL bytes, which PostgreSQL cannot store."""
    return value.replace("\x00", "")[:limit]


def _small(data: dict[str, Any] | None) -> dict[str, Any]:
    """Keep an entry's data small and storable: short strings, plain scalars."""
    kept: dict[str, Any] = {}
    for key, value in (data or {}).items():
        if isinstance(value, str):
            kept[_clean(str(key), 60)] = _clean(value, DATA_VALUE_CHARS)
        elif value is None or isinstance(value, bool | int):
            kept[_clean(str(key), 60)] = value
        else:
            kept[_clean(str(key), 60)] = _clean(str(value), DATA_VALUE_CHARS)
    return kept


def record(
    action: str,
    *,
    door: str,
    actor: str = "",
    token: str = "",
    address: str = "",
    target: str = "",
    status: int = 200,
    outcome: str | None = None,
    organization_id: int | None = None,
    organization_slug: str = "",
    data: dict[str, Any] | None = None,
) -> AuditEntry:
    """Append one entry to the chain, after the newest one, in its own transaction."""
    entry = AuditEntry(
        organization_id=organization_id,
        organization_slug=_clean(organization_slug, 64),
        actor=_clean(actor, 160),
        token=_clean(token, 100),
        address=_clean(address, 64),
        door=Door(door),
        action=_clean(action, 80),
        object=_clean(target, 300),
        status=status,
        outcome=Outcome(outcome or outcome_of(status)),
        data=_small(data),
    )
    with transaction.atomic():
        with connection.cursor() as cursor:
            if connection.vendor == "postgresql":
                # Held to commit: nobody reads the newest hash until this entry is in, and ids follow the chain.
                cursor.execute("SELECT pg_advisory_xact_lock(%s)", [CHAIN_LOCK])
            cursor.execute(f"SELECT hash FROM {AuditEntry._meta.db_table} ORDER BY id DESC LIMIT 1")
            row = cursor.fetchone()
        # The time is taken under the lock, so it never goes back along the chain.
        entry.ts = timezone.now()
        entry.prev_hash = row[0] if row else GENESIS
        entry.hash = entry.digest()
        entry.save(force_insert=True)
    return entry


def record_quietly(action: str, **fields: Any) -> AuditEntry | None:
    """Append an entry for an action that already happened; a failed write is logged, never raised to its caller."""
    try:
        return record(action, **fields)
    except Exception:
        # The action is done: refusing its answer now would not undo it, so the loss is reported instead.
        log.exception("audit entry for %s could not be written", action)
        return None


def organization_of_robot(robot_id: str) -> tuple[int | None, str]:
    """Return the id and slug of a robot's organization, or (None, "") when there is no such robot."""
    from robots.models import Robot

    row = Robot.objects.filter(id=robot_id).values_list("organization_id", "organization__slug").first()
    return (row[0], row[1] or "") if row else (None, "")


def organization_id(slug: str) -> int | None:
    """Return the id of the organization with this slug, None when there is none."""
    from teams.models import Organization

    return Organization.objects.filter(slug=slug).values_list("id", flat=True).first()


def organization_slug(organization_id: int | None) -> str:
    """Return an organization's slug ("" for none or a deleted one)."""
    from teams.models import Organization

    if organization_id is None:
        return ""
    return Organization.objects.filter(id=organization_id).values_list("slug", flat=True).first() or ""


@dataclass(frozen=True)
class Broken:
    """The first link of the chain that does not hold."""

    id: int
    reason: str


@dataclass(frozen=True)
class Verified:
    """What a walk of the chain found."""

    rows: int
    broken: Broken | None


def _rows(batch: int) -> Iterator[tuple[Any, ...]]:
    """Yield every entry's id, hashes and chained fields in id order, a batch at a time from a server-side cursor."""
    fields = ("id", "prev_hash", "hash", *CHAINED)
    yield from AuditEntry.objects.order_by("id").values_list(*fields).iterator(chunk_size=batch)


def verify_chain(batch: int = 5000) -> Verified:
    """Recompute every entry's hash and its link to the one before; stop at the first that does not hold."""
    rows = 0
    expected: str | None = None
    for values in _rows(batch):
        entry_id, prev_hash, stored = values[0], values[1], values[2]
        if expected is None:
            anchor = AuditAnchor.objects.filter(first_id=entry_id).values_list("prev_hash", flat=True).first()
            expected = anchor or GENESIS
            if prev_hash != expected:
                missing = "no anchor says entries before it were removed" if anchor is None else "its anchor differs"
                return Verified(rows, Broken(entry_id, f"prev_hash mismatch: the first entry, and {missing}"))
        elif prev_hash != expected:
            return Verified(rows, Broken(entry_id, "prev_hash mismatch: an entry before it was removed or changed"))
        entry = AuditEntry(id=entry_id, prev_hash=prev_hash, **dict(zip(CHAINED, values[3:], strict=True)))
        if entry.digest() != stored:
            return Verified(rows, Broken(entry_id, "hash mismatch: the entry's fields were changed"))
        expected = stored
        rows += 1
    return Verified(rows, None)


def prune_entries(older_than: timedelta | None = None) -> int:
    """Delete entries past the retention age, anchor the chain at the first kept one, and return how many went."""
    if older_than is None:
        older_than = timedelta(days=settings.BRIDGEOS["AUDIT_RETENTION_DAYS"])
    cutoff = timezone.now() - older_than
    with transaction.atomic():
        # The retention run itself is an entry, so the chain never empties and the cut is on record.
        mark = record("audit.retention", door="system", data={"older_than_days": older_than.days})
        doomed = AuditEntry.objects.filter(ts__lt=cutoff, id__lt=mark.id)
        last = doomed.order_by("-id").values_list("id", flat=True).first()
        if last is None:
            return 0
        first_kept = AuditEntry.objects.filter(id__gt=last).order_by("id").values_list("id", "prev_hash").first()
        assert first_kept is not None  # the retention entry at least
        with connection.cursor() as cursor:
            if connection.vendor == "postgresql":
                # Only for this transaction: the append-only trigger lets retention (and nothing else) delete.
                cursor.execute("SET LOCAL bridgeos.audit_retention = 'on'")
        removed, _ = AuditEntry.objects.filter(id__lte=last).delete()
        AuditAnchor.objects.create(first_id=first_kept[0], prev_hash=first_kept[1], removed=removed)
    return removed


def _address(client: Any) -> str:
    """Return the address of an ASGI scope's client ("" when unknown)."""
    return str(client[0]) if client else ""


def record_client_command(actor: Any, event: str, robot_id: str, outcome: str, client: Any = None) -> None:
    """Write a command a client sent over /ws/client/ (a relayed event or a config change)."""
    organization_id, slug = organization_of_robot(robot_id)
    token = getattr(actor, "token", None)
    record_quietly(
        f"ws.{event}",
        door="ws",
        actor=actor.user.get_username() if actor is not None else "",
        token=(token.name or f"token-{token.pk}") if token is not None else "",
        address=_address(client),
        target=f"robot/{robot_id}",
        status={"ok": 200, "denied": 403, "not_found": 404, "invalid": 400}.get(outcome, 502),
        outcome=outcome,
        organization_id=organization_id,
        organization_slug=slug,
    )


def record_bridge_open(kind: str, robot_id: str, user_id: int | None, client: Any = None) -> None:
    """Write a bridge session opened to a robot, or refused (no user)."""
    from django.contrib.auth import get_user_model

    organization_id, slug = organization_of_robot(robot_id)
    name = ""
    if user_id is not None:
        name = get_user_model().objects.filter(pk=user_id).values_list("username", flat=True).first() or ""
    record_quietly(
        "bridge.open",
        door="bridge",
        actor=name,
        address=_address(client),
        target=f"robot/{robot_id}",
        status=200 if user_id is not None else 403,
        organization_id=organization_id,
        organization_slug=slug,
        data={"kind": kind},
    )


def record_registry_push(repository: str, tag: str, digest: str, actor: str) -> None:
    """Write one tag pushed to the registry, by its pusher, in the organization its namespace names."""
    from teams.models import Organization

    namespace = repository.partition("/")[0]
    organization_id = Organization.objects.filter(slug=namespace).values_list("id", flat=True).first()
    record_quietly(
        "registry.push",
        door="registry",
        actor=actor,
        target=f"image/{repository}:{tag}",
        organization_id=organization_id,
        organization_slug=namespace if organization_id is not None else "",
        data={"digest": digest},
    )

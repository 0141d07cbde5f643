"""The slug of a user's personal organization, made from their username (a pure rule the migration shares)."""

from __future__ import annotations

import re
from collections.abc import Callable

MAX_SLUG = 64
# Also a registry namespace, so it follows Distribution's repository-name rules (lowercase, no '/').
SLUG_PATTERN = r"^[a-z0-9]+(?:[._-][a-z0-9]+)*$"


def is_slug(text: str) -> bool:
    """Tell whether a text may name an organization as it is."""
    return len(text) <= MAX_SLUG and re.fullmatch(SLUG_PATTERN, text) is not None


def personal_slug(username: str, user_id: int, taken: Callable[[str], bool]) -> str:
    """Return a free organization slug for a user: their username when it is one, else the closest free one.

    Registry namespaces are organization slugs, so a user whose name is already a valid slug keeps
    pushing where they pushed before organizations existed.
    """
    if is_slug(username) and not taken(username):
        return username
    base = re.sub(r"[^a-z0-9]+", "-", username.lower()).strip("-")[: MAX_SLUG - 8] or f"user-{user_id}"
    candidate, n = base, 1
    while taken(candidate):
        n += 1
        candidate = f"{base}-{n}"
    return candidate


def member_object(slug: str, username: object) -> str:
    """Name a membership as the audit trail writes its object: organization/lab/member/ada."""
    return f"organization/{slug}/member/{str(username or '')[:150]}"

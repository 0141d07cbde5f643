"""Robot labels and selectors: validating, parsing and matching them, and the query that finds a group.

Pure functions over plain data; the rules of one label are the agent's (``bridgeos_agent.labels``),
so `bridgeos-agent run --label` and the cloud refuse the same things.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Literal

from django.core.exceptions import ValidationError
from django.db import connection
from django.db.models import Q
from django.db.models.fields.json import KeyTextTransform
from django.db.models.lookups import Exact

from bridgeos_agent.labels import LabelError, key_problem, label_problems, value_problem
from bridgeos_agent.labels import parse_labels as parse_label_text

__all__ = ["Selector", "Term", "matches", "parse_labels", "parse_selector", "selector_q", "validate_labels"]

Op = Literal["=", "!=", "has", "lacks"]


def validate_labels(labels: object, field: str = "labels") -> dict[str, str]:
    """Return a valid labels mapping as a plain dict; raise ValidationError naming each bad key under ``field``."""
    problems = label_problems(labels)
    if problems:
        raise ValidationError({field: problems})
    assert isinstance(labels, Mapping)
    return dict(labels)


def parse_labels(text: str, field: str = "labels") -> dict[str, str]:
    """Parse `k=v,k2=v2` into valid labels; raise ValidationError naming the bad pair under ``field``."""
    try:
        return parse_label_text(text)
    except LabelError as exc:
        raise ValidationError({field: [str(exc)]}) from None


@dataclass(frozen=True)
class Term:
    """One condition of a selector: `k=v`, `k!=v`, `k` (has the key) or `!k` (lacks it)."""

    op: Op
    key: str
    value: str = ""

    def holds(self, labels: Mapping[str, str]) -> bool:
        """Tell whether labels meet this condition."""
        if self.op == "=":
            return labels.get(self.key) == self.value
        if self.op == "!=":
            return labels.get(self.key) != self.value
        if self.op == "has":
            return self.key in labels
        return self.key not in labels

    def __str__(self) -> str:
        return {"=": f"{self.key}={self.value}", "!=": f"{self.key}!={self.value}", "has": self.key}.get(
            self.op, f"!{self.key}"
        )


@dataclass(frozen=True)
class Selector:
    """A group of robots named by terms that must all hold."""

    terms: tuple[Term, ...]

    def __str__(self) -> str:
        return ",".join(str(term) for term in self.terms)


def parse_term(text: str) -> Term:
    """Parse one selector term; raise LabelError naming it when it is malformed."""
    term = text.strip()
    if term.startswith("!") and "=" not in term:
        op: Op = "lacks"
        key, value = term[1:].strip(), ""
    elif "!=" in term:
        op = "!="
        key, _, value = term.partition("!=")
    elif "=" in term:
        op = "="
        key, _, value = term.partition("=")
    else:
        op, key, value = "has", term, ""
    key, value = key.strip(), value.strip()
    problem = key_problem(key) or (value_problem(key, value) if op in ("=", "!=") else None)
    if problem or (op in ("=", "!=") and "=" in value):
        raise LabelError(f"selector term {term!r} is invalid: {problem or 'one operator per term'}")
    return Term(op, key, value)


def parse_selector(text: str, field: str = "selector") -> Selector:
    """Parse `site=lab,model!=x,gpu,!retired`; raise ValidationError naming the bad term under ``field``."""
    if not text.strip():
        raise ValidationError({field: ["a selector needs at least one term, e.g. site=lab"]})
    try:
        return Selector(tuple(parse_term(term) for term in text.split(",")))
    except LabelError as exc:
        raise ValidationError({field: [str(exc)]}) from None


def matches(labels: Mapping[str, str], selector: Selector | str) -> bool:
    """Tell whether labels meet every term of a selector."""
    chosen = parse_selector(selector) if isinstance(selector, str) else selector
    return all(term.holds(labels) for term in chosen.terms)


def selector_q(selector: Selector | str, field: str = "labels", *, containment: bool | None = None) -> Q:
    """Return the query for robots whose labels meet a selector.

    Equalities are one `labels @> {...}` where the database has JSON containment (PostgreSQL, whose
    GIN index serves it); elsewhere (the embedded SQLite) each is a comparison of the key's text.
    """
    chosen = parse_selector(selector) if isinstance(selector, str) else selector
    if containment is None:
        containment = connection.features.supports_json_field_contains
    equal: dict[str, str] = {}
    for term in chosen.terms:
        if term.op == "=" and equal.setdefault(term.key, term.value) != term.value:
            # Two values for one key (site=a,site=b): no robot holds both.
            return Q(pk__in=[])
    q = Q()
    if equal:
        q = Q(**{f"{field}__contains": equal}) if containment else _all_equal(field, equal)
    for term in chosen.terms:
        if term.op == "!=":
            same = (
                Q(**{f"{field}__contains": {term.key: term.value}})
                if containment
                else _all_equal(field, {term.key: term.value})
            )
            q &= ~same
        elif term.op == "has":
            q &= Q(**{f"{field}__has_key": term.key})
        elif term.op == "lacks":
            q &= ~Q(**{f"{field}__has_key": term.key})
    return q


def _all_equal(field: str, labels: dict[str, str]) -> Q:
    """Return the query for labels holding every one of these key-values, without JSON containment."""
    q = Q()
    for key, value in labels.items():
        # has_key first, so the comparison never meets a missing key's NULL (which a negation would keep out).
        q &= Q(**{f"{field}__has_key": key}) & Q(Exact(KeyTextTransform(key, field), value))
    return q

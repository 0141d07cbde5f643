"""Robot labels (`key=value`): their rules and their `k=v,k2=v2` text form, shared by the agent and the cloud."""

from __future__ import annotations

import re
from collections.abc import Mapping

__all__ = ["MAX_LABELS", "MAX_LENGTH", "LabelError", "label_problems", "parse_label_pairs", "parse_labels"]

MAX_LABELS = 64
MAX_LENGTH = 63
# Kubernetes-like: keys lowercase, values may be uppercase and empty; both start and end alphanumeric.
KEY_PATTERN = re.compile(r"^[a-z0-9]([a-z0-9._-]*[a-z0-9])?$")
VALUE_PATTERN = re.compile(r"^([A-Za-z0-9]([A-Za-z0-9._-]*[A-Za-z0-9])?)?$")
KEY_RULE = "lowercase letters, digits, '-', '_' or '.', starting and ending with a letter or digit, at most 63"
VALUE_RULE = "letters, digits, '-', '_' or '.', starting and ending with a letter or digit, at most 63 (or empty)"


class LabelError(ValueError):
    """Labels or their text that break the rules; the message names the offending key or term."""


def key_problem(key: object) -> str | None:
    """Say what is wrong with a label key, or None."""
    if not isinstance(key, str):
        return f"label key {key!r} is not a string"
    if len(key) > MAX_LENGTH or not KEY_PATTERN.match(key):
        return f"label key {key!r} is invalid: use {KEY_RULE} characters"
    return None


def value_problem(key: str, value: object) -> str | None:
    """Say what is wrong with the value of a label, or None."""
    if not isinstance(value, str):
        return f"label {key!r}: value {value!r} is not a string"
    if len(value) > MAX_LENGTH or not VALUE_PATTERN.match(value):
        return f"label {key!r}: value {value!r} is invalid: use {VALUE_RULE} characters"
    return None


def label_problems(labels: object) -> list[str]:
    """List what is wrong with a labels mapping, each problem naming its key; empty when it is valid."""
    if not isinstance(labels, Mapping):
        return ["labels must be an object of key: value strings"]
    problems = []
    if len(labels) > MAX_LABELS:
        problems.append(f"at most {MAX_LABELS} labels, not {len(labels)}")
    for key, value in labels.items():
        problem = key_problem(key) or value_problem(key, value)
        if problem:
            problems.append(problem)
    return problems


def parse_label_pairs(text: str) -> list[tuple[str, str]]:
    """Split `k=v,k2=v2` into its pairs in order (blank text: none), without checking the rules."""
    pairs = []
    for term in (part.strip() for part in text.split(",")):
        if not term and not text.strip():
            continue
        key, sep, value = term.partition("=")
        if not sep:
            raise LabelError(f"label {term!r} has no '=': write key=value")
        pairs.append((key.strip(), value.strip()))
    return pairs


def parse_labels(text: str | list[str]) -> dict[str, str]:
    """Parse `k=v,k2=v2` (or several such texts) into valid labels; raise LabelError naming the bad one."""
    texts = [text] if isinstance(text, str) else text
    labels: dict[str, str] = {}
    for key, value in (pair for each in texts for pair in parse_label_pairs(each)):
        if key in labels and labels[key] != value:
            raise LabelError(f"label {key!r} is given twice, as {labels[key]!r} and {value!r}")
        labels[key] = value
    problems = label_problems(labels)
    if problems:
        raise LabelError("; ".join(problems))
    return labels

"""Share fixtures for the agent package's tests."""

from __future__ import annotations

import copy
import json
from importlib import resources
from typing import Any

import pytest

_SAMPLE = json.loads(
    resources.files("bridgeos_agent").joinpath("samples").joinpath("people_detection.json").read_text()
)


@pytest.fixture
def sample() -> dict[str, Any]:
    """Return a fresh, mutable copy of the people-detection sample Skill config."""
    return copy.deepcopy(_SAMPLE)

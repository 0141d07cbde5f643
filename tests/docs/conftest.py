"""The documentation's generator, loaded from scripts/ as the tests' one way to call it."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path
from types import ModuleType

import pytest

ROOT = Path(__file__).resolve().parents[2]
GENERATOR = ROOT / "scripts" / "docs_reference.py"


def load_generator() -> ModuleType:
    """Import scripts/docs_reference.py (scripts/ is no package)."""
    spec = importlib.util.spec_from_file_location("docs_reference", GENERATOR)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules.setdefault("docs_reference", module)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="session")
def generator() -> ModuleType:
    """Return the reference pages' generator."""
    return load_generator()


@pytest.fixture(scope="session")
def rendered(generator: ModuleType) -> dict[str, str]:
    """Render every reference page from the code once for the session."""
    return generator.render()

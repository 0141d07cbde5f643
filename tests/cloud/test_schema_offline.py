"""The OpenAPI schema is made without the database: test modules build it at import, before any test database."""

from __future__ import annotations

import contextlib
import io
from typing import Any

import pytest
from django.db.backends.base.base import BaseDatabaseWrapper
from drf_spectacular.generators import SchemaGenerator


def test_the_schema_is_generated_without_touching_the_database(monkeypatch: pytest.MonkeyPatch) -> None:
    # A view whose get_queryset queries while the schema is made would, at collection, open the
    # connection pool on the real database, and every test after it would run there instead of on
    # the test database. drf-spectacular turns such an error into a warning, so count the attempts.
    opened: list[str] = []

    def refuse(self: Any) -> None:
        opened.append(self.alias)
        raise RuntimeError("no database while the schema is made")

    monkeypatch.setattr(BaseDatabaseWrapper, "ensure_connection", refuse)
    with contextlib.redirect_stderr(io.StringIO()):
        paths = SchemaGenerator().get_schema(request=None, public=True)["paths"]
    assert opened == []
    assert "/api/releases" in paths and "/api/robot" in paths

"""Admin of the audit trail: read-only, since the trail is append-only."""

from __future__ import annotations

from typing import Any

from django.contrib import admin
from django.http import HttpRequest

from .models import AuditAnchor, AuditEntry


class ReadOnly(admin.ModelAdmin):
    """Show rows; never add, change or delete one."""

    def has_add_permission(self, request: HttpRequest) -> bool:
        return False

    def has_change_permission(self, request: HttpRequest, obj: Any = None) -> bool:
        return False

    def has_delete_permission(self, request: HttpRequest, obj: Any = None) -> bool:
        return False


@admin.register(AuditEntry)
class AuditEntryAdmin(ReadOnly):
    list_display = ("id", "ts", "door", "actor", "token", "action", "object", "status", "outcome", "organization_slug")
    list_filter = ("door", "outcome")
    search_fields = ("actor", "action", "object")


@admin.register(AuditAnchor)
class AuditAnchorAdmin(ReadOnly):
    list_display = ("first_id", "removed", "created_at")

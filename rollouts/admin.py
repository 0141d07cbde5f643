"""Admin of releases and rollouts: read-only, since both are made and steered through the Robot API; holds editable."""

from __future__ import annotations

from typing import Any

from django.contrib import admin
from django.http import HttpRequest

from .models import Release, Rollout, RolloutRobot, UpdateHold


@admin.register(Release)
class ReleaseAdmin(admin.ModelAdmin):
    list_display = ["skill_id", "number", "name", "organization", "created_by_name", "created_at"]
    list_filter = ["organization"]
    search_fields = ["skill_id", "name", "organization__slug", "created_by_name"]
    list_select_related = ["organization"]
    readonly_fields = [
        "organization",
        "skill_id",
        "number",
        "name",
        "notes",
        "config",
        "created_by",
        "created_by_name",
        "created_at",
    ]

    def has_add_permission(self, request: HttpRequest) -> bool:
        return False

    def has_change_permission(self, request: HttpRequest, obj: Any = None) -> bool:
        return False

    def has_delete_permission(self, request: HttpRequest, obj: Any = None) -> bool:
        return False


class RolloutRobotInline(admin.TabularInline):
    model = RolloutRobot
    fields = ["robot", "batch", "status", "reason", "touched", "started_at", "finished_at"]
    readonly_fields = fields
    extra = 0
    can_delete = False

    def has_add_permission(self, request: HttpRequest, obj: Any = None) -> bool:
        return False


@admin.register(Rollout)
class RolloutAdmin(admin.ModelAdmin):
    """Rollouts are started and steered through the Robot API and the dashboard; the admin shows them."""

    list_display = ["id", "release", "selector", "state", "batch", "organization", "created_by_name", "created_at"]
    list_filter = ["state", "organization"]
    search_fields = ["selector", "release__skill_id", "organization__slug", "created_by_name"]
    list_select_related = ["release", "organization"]
    inlines = [RolloutRobotInline]

    def get_readonly_fields(self, request: HttpRequest, obj: Any = None) -> list[str]:
        return [field.name for field in Rollout._meta.fields]

    def has_add_permission(self, request: HttpRequest) -> bool:
        return False

    def has_delete_permission(self, request: HttpRequest, obj: Any = None) -> bool:
        return False


@admin.register(UpdateHold)
class UpdateHoldAdmin(admin.ModelAdmin):
    list_display = ["robot", "holder", "reason", "until", "created_at"]
    search_fields = ["robot__id", "holder"]

"""Admin of robots: tokens are shown once on creation and can be rotated."""

from __future__ import annotations

from typing import Any

from django.contrib import admin, messages
from django.db.models import QuerySet
from django.http import HttpRequest

from monitoring.services import record_event

from . import services
from .models import ApiToken, Robot


@admin.register(Robot)
class RobotAdmin(admin.ModelAdmin):
    list_display = ["id", "name", "owner", "status", "connected", "last_seen"]
    list_filter = ["status", "connected"]
    search_fields = ["id", "name", "owner__username"]
    readonly_fields = ["connected", "last_seen", "created_at"]
    actions = ["rotate_tokens"]

    def get_readonly_fields(self, request: HttpRequest, obj: Robot | None = None) -> list[str]:
        # The id is the robot's identity on the wire; changing it would orphan the agent.
        return [*self.readonly_fields, "id"] if obj else list(self.readonly_fields)

    def save_model(self, request: HttpRequest, obj: Robot, form: Any, change: bool) -> None:
        token = None if change else obj.issue_token()
        super().save_model(request, obj, form, change)
        if change and form.changed_data:
            record_event(
                f"Robot {obj.id} changed in the admin by {request.user.get_username()}",
                robot_id=obj.id,
                kind="robot_updated",
                data={"fields": form.changed_data, "user": request.user.get_username()},
            )
        if token:
            messages.warning(request, f"Token of robot {obj.id} (copy it now, it is shown only once): {token}")

    @admin.action(description="Rotate the token of the selected robots")
    def rotate_tokens(self, request: HttpRequest, queryset: QuerySet[Robot]) -> None:
        for robot in queryset:
            token = services.rotate_token(robot)
            messages.warning(request, f"New token of robot {robot.id} (shown only once): {token}")


@admin.register(ApiToken)
class ApiTokenAdmin(admin.ModelAdmin):
    """API tokens can be reviewed and revoked (deleted), never read: only their hash is kept."""

    list_display = ["user", "created_at", "expires_at"]
    search_fields = ["user__username"]
    readonly_fields = ["user", "created_at", "expires_at"]

    def has_add_permission(self, request: HttpRequest) -> bool:
        return False

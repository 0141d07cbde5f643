"""Admin of robots: tokens are shown once on creation and can be rotated; labels are edited, searched and filtered.

A robot is deleted as the API deletes it (``services.delete_robot``): with all it owns, its connection closed.
"""

from __future__ import annotations

from typing import Any

from django.conf import settings
from django.contrib import admin, messages
from django.core.exceptions import ValidationError
from django.db import connection
from django.db.models import Count, QuerySet
from django.http import HttpRequest

from monitoring.services import record_event

from . import rotation, services
from .labels import selector_q
from .models import ApiToken, Robot


def label_pairs(limit: int = 100) -> list[tuple[str, str]]:
    """Return the distinct labels robots carry (key, value), in order, at most ``limit``."""
    if connection.vendor != "postgresql":
        found = {pair for labels in Robot.objects.values_list("labels", flat=True) for pair in labels.items()}
        return sorted(found)[:limit]
    with connection.cursor() as cursor:
        cursor.execute(
            "SELECT DISTINCT e.key, e.value FROM robots_robot, jsonb_each_text(labels) e ORDER BY 1, 2 LIMIT %s",
            [limit],
        )
        return [(key, value) for key, value in cursor.fetchall()]


class LabelFilter(admin.SimpleListFilter):
    """Filter robots by one of the labels robots carry (key=value)."""

    title = "label"
    parameter_name = "label"

    def lookups(self, request: HttpRequest, model_admin: admin.ModelAdmin) -> list[tuple[str, str]]:
        pairs = [f"{key}={value}" for key, value in label_pairs(limit=100)]
        return [(pair, pair) for pair in pairs]

    def queryset(self, request: HttpRequest, queryset: QuerySet[Robot]) -> QuerySet[Robot]:
        if not self.value():
            return queryset
        try:
            return queryset.filter(selector_q(self.value()))
        except ValidationError:
            return queryset.none()


@admin.register(Robot)
class RobotAdmin(admin.ModelAdmin):
    list_display = ["id", "name", "organization", "owner", "status", "connected", "last_seen", "labels_text"]
    list_filter = ["status", "connected", "organization", LabelFilter]
    # A search with '=' is a selector (site=lab,!retired); else the text is looked for in the labels too.
    search_fields = ["id", "name", "owner__username", "organization__slug", "labels"]
    search_help_text = "Id, name, owner, organization or label text; a selector such as site=lab,model!=x."
    autocomplete_fields = ["organization"]
    readonly_fields = ["connected", "last_seen", "created_at"]
    actions = ["rotate_tokens"]

    @admin.display(description="labels")
    def labels_text(self, robot: Robot) -> str:
        return ", ".join(f"{key}={value}" for key, value in sorted(robot.labels.items()))

    def get_search_results(
        self, request: HttpRequest, queryset: QuerySet[Robot], search_term: str
    ) -> tuple[QuerySet[Robot], bool]:
        if "=" in search_term:
            try:
                return queryset.filter(selector_q(search_term)), False
            except ValidationError as exc:
                messages.error(request, "; ".join(exc.messages))
                return queryset.none(), False
        return super().get_search_results(request, queryset, search_term)

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

    def get_deleted_objects(
        self, objs: Any, request: HttpRequest
    ) -> tuple[list[Any], dict[str, int], set[str], list[Any]]:
        """List the robots and count the rows each takes with it, without loading those rows.

        Django's own confirmation loads every related row to list it: a robot's metric points run
        to millions. What a robot owns goes with it, as through the API: the robot's own delete
        permission decides, not one per kind of row (its subnets and certificate have none).
        """
        robots = list(objs)
        owned = owned_rows([robot.pk for robot in robots])
        totals: dict[str, int] = {str(Robot._meta.verbose_name_plural): len(robots)}
        listed: list[Any] = []
        for robot in robots:
            rows = owned.get(robot.pk, {})
            for name, count in rows.items():
                totals[name] = totals.get(name, 0) + count
            named = f"{robot.name} ({robot.pk})" if robot.name and robot.name != robot.pk else robot.pk
            listed.append(f"{Robot._meta.verbose_name.capitalize()}: {named}")
            if rows:
                listed.append([f"{n} {name}" for name, n in rows.items()])
        return listed, totals, set(), []

    def delete_model(self, request: HttpRequest, obj: Robot) -> None:
        services.delete_robot(obj)

    def delete_queryset(self, request: HttpRequest, queryset: QuerySet[Robot]) -> None:
        for robot in queryset:
            services.delete_robot(robot)

    @admin.action(description="Rotate the token of the selected robots (connected ones re-key live)")
    def rotate_tokens(self, request: HttpRequest, queryset: QuerySet[Robot]) -> None:
        grace_s = settings.BRIDGEOS["TOKEN_ROTATION_GRACE_S"]
        rotated = rotation.rotate_tokens(queryset, grace_s=grace_s)
        for each in rotated:
            messages.warning(request, f"New token of robot {each.robot.id} (shown only once): {each.token}")
        if grace_s <= 0:
            messages.info(request, "The old tokens, and the connections made with them, ended now.")
            return
        live = sum(each.sent_live for each in rotated)
        messages.info(
            request,
            f"{live} of {len(rotated)} robot(s) were connected and were given their new token live; the old tokens "
            f"work for {grace_s:g} s more: hand the others theirs before then.",
        )


def owned_rows(robot_ids: list[str]) -> dict[str, dict[str, int]]:
    """Count the rows that point at each of these robots directly, by kind (plural name): one query a kind."""
    owned: dict[str, dict[str, int]] = {}
    for relation in Robot._meta.related_objects:
        if not (relation.one_to_many or relation.one_to_one):
            continue
        model, field = relation.related_model, relation.field.name
        name = str(model._meta.verbose_name_plural)
        grouped = (
            model._base_manager.filter(**{f"{field}__in": robot_ids})
            .order_by()
            .values_list(field)
            .annotate(rows=Count("pk"))
        )
        for robot_id, rows in grouped:
            owned.setdefault(robot_id, {})[name] = rows
    return owned


@admin.register(ApiToken)
class ApiTokenAdmin(admin.ModelAdmin):
    """API tokens can be reviewed and revoked (deleted), never read: only their hash is kept."""

    list_display = ["user", "name", "organization", "role", "created_at", "expires_at"]
    list_filter = ["organization"]
    search_fields = ["user__username", "name", "organization__slug"]
    readonly_fields = ["user", "name", "organization", "role", "created_at", "expires_at"]

    def has_add_permission(self, request: HttpRequest) -> bool:
        return False

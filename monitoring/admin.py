"""Admin of metrics and events: browsable, filterable, read-only."""

from __future__ import annotations

from django.contrib import admin
from django.http import HttpRequest

from .models import Event, Metric


class ReadOnlyAdmin(admin.ModelAdmin):
    # Counting millions of rows on every page view is what makes big admin tables slow.
    show_full_result_count = False

    def has_add_permission(self, request: HttpRequest) -> bool:
        return False

    def has_change_permission(self, request: HttpRequest, obj: object = None) -> bool:
        return False


@admin.register(Metric)
class MetricAdmin(ReadOnlyAdmin):
    list_display = ["ts", "robot", "skill", "component", "name", "value"]
    list_filter = ["name"]
    search_fields = ["robot__id", "name", "skill", "component"]
    date_hierarchy = "ts"


@admin.register(Event)
class EventAdmin(ReadOnlyAdmin):
    list_display = ["ts", "level", "source", "kind", "robot", "skill", "component", "message"]
    list_filter = ["level", "source", "kind"]
    search_fields = ["robot__id", "message", "skill", "component"]
    date_hierarchy = "ts"

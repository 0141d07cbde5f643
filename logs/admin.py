"""Admin of component logs: browsable, filterable, read-only."""

from __future__ import annotations

from django.contrib import admin

from monitoring.admin import ReadOnlyAdmin

from .models import ComponentLog, DroppedLines


@admin.register(ComponentLog)
class ComponentLogAdmin(ReadOnlyAdmin):
    list_display = ["ts", "robot_id", "skill", "component", "location", "seq", "stream", "level", "text"]
    list_filter = ["location", "stream", "level"]
    search_fields = ["robot_id", "skill", "component"]
    date_hierarchy = "ts"


@admin.register(DroppedLines)
class DroppedLinesAdmin(ReadOnlyAdmin):
    list_display = ["ts", "robot_id", "skill", "component", "location", "count"]
    search_fields = ["robot_id", "skill", "component"]

"""Admin of recordings: read-only views of what robots recorded."""

from __future__ import annotations

from django.contrib import admin

from .models import Recording


@admin.register(Recording)
class RecordingAdmin(admin.ModelAdmin):
    list_display = ("id", "robot", "status", "ros", "message_count", "size_bytes", "created_at")
    list_filter = ("status", "ros")
    search_fields = ("robot__id",)
    readonly_fields = [field.name for field in Recording._meta.fields]

"""Admin of skills, their components and the catalog."""

from __future__ import annotations

from django.contrib import admin

from .models import Component, Skill, SkillTemplate


class ComponentInline(admin.TabularInline):
    model = Component
    extra = 0
    fields = ["component_id", "location", "active_location", "status", "container", "resources"]


@admin.register(Skill)
class SkillAdmin(admin.ModelAdmin):
    list_display = ["skill_id", "name", "robot", "status", "updated_at"]
    list_filter = ["status"]
    search_fields = ["skill_id", "name", "robot__id"]
    list_select_related = ["robot"]
    inlines = [ComponentInline]


@admin.register(Component)
class ComponentAdmin(admin.ModelAdmin):
    list_display = ["component_id", "skill", "location", "active_location", "status", "updated_at"]
    list_filter = ["location", "active_location", "status"]
    search_fields = ["component_id", "skill__skill_id", "skill__robot__id"]
    list_select_related = ["skill"]


@admin.register(SkillTemplate)
class SkillTemplateAdmin(admin.ModelAdmin):
    list_display = ["name", "description", "created_at"]
    search_fields = ["name", "description"]

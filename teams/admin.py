"""Admin of organizations and their members' roles."""

from __future__ import annotations

from django.contrib import admin

from .models import Membership, Organization


class MembershipInline(admin.TabularInline):
    model = Membership
    extra = 1
    autocomplete_fields = ["user"]


@admin.register(Organization)
class OrganizationAdmin(admin.ModelAdmin):
    list_display = ["slug", "name", "personal_of", "created_at"]
    list_filter = [("personal_of", admin.EmptyFieldListFilter)]
    search_fields = ["slug", "name", "memberships__user__username"]
    autocomplete_fields = ["personal_of"]
    inlines = [MembershipInline]


@admin.register(Membership)
class MembershipAdmin(admin.ModelAdmin):
    list_display = ["organization", "user", "role", "created_at"]
    list_filter = ["role"]
    search_fields = ["organization__slug", "user__username"]
    autocomplete_fields = ["organization", "user"]

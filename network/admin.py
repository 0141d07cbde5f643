"""Admin of robots' networks: allocations and certificates can be reviewed; keys are never shown."""

from __future__ import annotations

from django.contrib import admin
from django.http import HttpRequest

from .models import ClientCertificate, Revocation, Subnet


class ReadOnly(admin.ModelAdmin):
    def has_add_permission(self, request: HttpRequest) -> bool:
        return False

    def has_change_permission(self, request: HttpRequest, obj: object = None) -> bool:
        return False

    def has_delete_permission(self, request: HttpRequest, obj: object = None) -> bool:
        # Deleting a robot frees its subnets and revokes its certificate; a bare row delete would do neither.
        return False


@admin.register(Subnet)
class SubnetAdmin(ReadOnly):
    list_display = ["robot", "kind", "network", "created_at"]
    list_filter = ["kind"]
    search_fields = ["robot__id", "network"]


@admin.register(ClientCertificate)
class ClientCertificateAdmin(ReadOnly):
    list_display = ["robot", "serial", "not_after", "created_at"]
    search_fields = ["robot__id", "serial"]
    exclude = ["key_pem"]


@admin.register(Revocation)
class RevocationAdmin(ReadOnly):
    list_display = ["robot_id", "serial", "reason", "revoked_at"]
    search_fields = ["robot_id", "serial"]

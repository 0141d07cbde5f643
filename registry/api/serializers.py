"""Serializers of the registry's token endpoint."""

from __future__ import annotations

from rest_framework import serializers


class TokenQuerySerializer(serializers.Serializer):
    """The query Distribution's clients send to the realm (docker adds account, client_id, offline_token)."""

    service = serializers.CharField(required=False, allow_blank=True, max_length=255)
    # Counted after splitting (a parameter may list several), in services.parse_scopes.
    scope = serializers.ListField(child=serializers.CharField(max_length=16384), required=False)
    account = serializers.CharField(required=False, allow_blank=True, max_length=255)
    client_id = serializers.CharField(required=False, allow_blank=True, max_length=255)
    offline_token = serializers.CharField(required=False, allow_blank=True, max_length=16)


class RegistryTokenSerializer(serializers.Serializer):
    """A signed JWT for the registry, under both names clients read it by, and its lifetime."""

    token = serializers.CharField()
    access_token = serializers.CharField()
    expires_in = serializers.IntegerField()
    issued_at = serializers.CharField()

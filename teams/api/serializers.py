"""Shapes of the Robot API's requests and answers about organizations, members and scoped tokens."""

from __future__ import annotations

from rest_framework import serializers

from ..roles import Role


class OrganizationSerializer(serializers.Serializer):
    slug = serializers.CharField()
    name = serializers.CharField()
    personal = serializers.BooleanField(help_text="A user's own organization, made with their account.")
    role = serializers.ChoiceField(Role.choices, allow_null=True, help_text="The role you act with there.")


class OrganizationCreateSerializer(serializers.Serializer):
    slug = serializers.CharField(max_length=64, help_text="Lowercase letters and digits; also a registry namespace.")
    name = serializers.CharField(max_length=200, required=False, default="")


class MemberSerializer(serializers.Serializer):
    username = serializers.CharField()
    role = serializers.ChoiceField(Role.choices)
    since = serializers.DateTimeField(read_only=True)


class MemberRoleSerializer(serializers.Serializer):
    role = serializers.ChoiceField(Role.choices)


class TokenSerializer(serializers.Serializer):
    id = serializers.IntegerField()
    name = serializers.CharField()
    user = serializers.CharField()
    organization = serializers.CharField(allow_null=True, help_text="None: a login token, acting with all your roles.")
    role = serializers.ChoiceField(Role.choices, allow_null=True, help_text="The most it may do; None: your role.")
    created_at = serializers.DateTimeField()
    expires_at = serializers.DateTimeField(allow_null=True, help_text="None: until revoked.")
    expired = serializers.BooleanField()


class TokenCreateSerializer(serializers.Serializer):
    name = serializers.CharField(max_length=100)
    organization = serializers.CharField(max_length=64, help_text="Slug of one of your organizations.")
    role = serializers.ChoiceField(Role.choices, help_text="At most your role in that organization.")
    expires_at = serializers.DateTimeField(required=False, allow_null=True, help_text="Default: until revoked.")
    expires_in_days = serializers.IntegerField(required=False, allow_null=True)


class TokenCreatedSerializer(TokenSerializer):
    key = serializers.CharField(help_text="Send as `Authorization: Token <key>`; shown only this once.")

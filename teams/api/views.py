"""The Robot API about organizations, their members and scoped API tokens: thin doors onto teams.services."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, TypeVar

from django.core.exceptions import ValidationError as DjangoValidationError
from drf_spectacular.utils import OpenApiResponse, extend_schema
from rest_framework import status
from rest_framework.exceptions import PermissionDenied, ValidationError
from rest_framework.request import Request
from rest_framework.response import Response
from rest_framework.views import APIView

from audit.middleware import describe
from robots.access import actor_of

from .. import services, tokens
from ..models import Organization
from ..naming import member_object
from ..roles import Right
from .serializers import (
    MemberRoleSerializer,
    MemberSerializer,
    OrganizationCreateSerializer,
    OrganizationSerializer,
    TokenCreatedSerializer,
    TokenCreateSerializer,
    TokenSerializer,
)

T = TypeVar("T")
REFUSED = {400: OpenApiResponse(description="Invalid request"), 403: OpenApiResponse(), 404: OpenApiResponse()}


def checked(call: Callable[[], T]) -> T:
    """Run a service call, turning its field errors into a DRF 400."""
    try:
        return call()
    except DjangoValidationError as exc:
        raise ValidationError(getattr(exc, "message_dict", {"non_field_errors": exc.messages})) from exc


def organization_row(organization: Organization, role: str | None) -> dict[str, Any]:
    """Return an organization as the API lists it, with the role the request acts with there."""
    personal = organization.personal_of_id is not None
    return {"slug": organization.slug, "name": organization.name, "personal": personal, "role": role}


class OrganizationListView(APIView):
    """List the organizations you reach with your role in each, or make a team organization where you are admin."""

    @extend_schema(responses={200: OrganizationSerializer(many=True)})
    def get(self, request: Request) -> Response:
        rows = services.reachable_organizations(actor_of(request))
        return Response([organization_row(organization, role) for organization, role in rows])

    @extend_schema(request=OrganizationCreateSerializer, responses={201: OrganizationSerializer, **REFUSED})
    def post(self, request: Request) -> Response:
        actor = actor_of(request)
        if actor.token is not None and actor.token.organization_id is not None:
            raise PermissionDenied("A token scoped to one organization cannot make another.")
        form = OrganizationCreateSerializer(data=request.data)
        form.is_valid(raise_exception=True)
        data = form.validated_data
        organization = checked(lambda: services.create_organization(request.user, data["slug"], data["name"]))
        return Response(organization_row(organization, "admin"), status=status.HTTP_201_CREATED)


class OrganizationDetailView(APIView):
    """Show one of your organizations."""

    @extend_schema(responses={200: OrganizationSerializer, 404: OpenApiResponse()})
    def get(self, request: Request, slug: str) -> Response:
        actor = actor_of(request)
        organization = services.organization_for(actor, slug)
        return Response(organization_row(organization, actor.role_in(organization.id)))


class MemberListView(APIView):
    """List an organization's members and roles (viewer), or add a member (admin)."""

    @extend_schema(responses={200: MemberSerializer(many=True), 404: OpenApiResponse()})
    def get(self, request: Request, slug: str) -> Response:
        organization = services.organization_for(actor_of(request), slug)
        return Response([services.member_row(m) for m in services.members(organization)])

    @extend_schema(request=MemberSerializer, responses={201: MemberSerializer, **REFUSED})
    def post(self, request: Request, slug: str) -> Response:
        asked = request.data if isinstance(request.data, dict) else {}
        describe(
            request, "member.add", member_object(slug, asked.get("username")), role=str(asked.get("role", ""))[:20]
        )
        organization = services.organization_for(actor_of(request), slug, Right.ADMINISTER)
        form = MemberSerializer(data=request.data)
        form.is_valid(raise_exception=True)
        data = form.validated_data
        membership = checked(lambda: services.add_member(organization, data["username"], data["role"]))
        return Response(services.member_row(membership), status=status.HTTP_201_CREATED)


class MemberDetailView(APIView):
    """Change a member's role (admin), or remove a member (admin, or the member themself)."""

    @extend_schema(request=MemberRoleSerializer, responses={200: MemberSerializer, **REFUSED})
    def patch(self, request: Request, slug: str, username: str) -> Response:
        asked = request.data if isinstance(request.data, dict) else {}
        describe(request, "member.role", member_object(slug, username), role=str(asked.get("role", ""))[:20])
        organization = services.organization_for(actor_of(request), slug, Right.ADMINISTER)
        form = MemberRoleSerializer(data=request.data)
        form.is_valid(raise_exception=True)
        membership = checked(lambda: services.change_role(organization, username, form.validated_data["role"]))
        return Response(services.member_row(membership))

    @extend_schema(request=None, responses={204: None, **REFUSED})
    def delete(self, request: Request, slug: str, username: str) -> Response:
        actor = actor_of(request)
        # Leaving is one's own choice: not a scoped token's, which may have leaked.
        scoped = actor.token is not None and actor.token.organization_id is not None
        leaving = username == request.user.get_username() and not scoped
        describe(request, "member.leave" if leaving else "member.remove", member_object(slug, username))
        organization = services.organization_for(actor, slug, Right.READ if leaving else Right.ADMINISTER)
        checked(lambda: services.remove_member(organization, username))
        return Response(status=status.HTTP_204_NO_CONTENT)


class OrganizationTokenListView(APIView):
    """List an organization's scoped tokens, of every member (admin; never their keys)."""

    @extend_schema(responses={200: TokenSerializer(many=True), 403: OpenApiResponse(), 404: OpenApiResponse()})
    def get(self, request: Request, slug: str) -> Response:
        organization = services.organization_for(actor_of(request), slug, Right.ADMINISTER)
        return Response([tokens.token_row(t) for t in tokens.organization_tokens(organization)])


class TokenListView(APIView):
    """List your API tokens (login ones too; a scoped token lists its organization's), or make a scoped one."""

    @extend_schema(responses={200: TokenSerializer(many=True)})
    def get(self, request: Request) -> Response:
        return Response([tokens.token_row(t) for t in tokens.tokens_of(actor_of(request))])

    @extend_schema(request=TokenCreateSerializer, responses={201: TokenCreatedSerializer, 400: OpenApiResponse()})
    def post(self, request: Request) -> Response:
        form = TokenCreateSerializer(data=request.data)
        form.is_valid(raise_exception=True)
        data = form.validated_data
        key, token = checked(
            lambda: tokens.make_token(
                actor_of(request),
                name=data["name"],
                organization_slug=data["organization"],
                role=data["role"],
                expires_at=data.get("expires_at"),
                expires_in_days=data.get("expires_in_days"),
            )
        )
        return Response({**tokens.token_row(token), "key": key}, status=status.HTTP_201_CREATED)


class TokenDetailView(APIView):
    """Revoke one of your tokens, or any token of an organization you administer; its live connections close."""

    @extend_schema(request=None, responses={204: None, 404: OpenApiResponse()})
    def delete(self, request: Request, token_id: int) -> Response:
        tokens.revoke_token(actor_of(request), token_id)
        return Response(status=status.HTTP_204_NO_CONTENT)

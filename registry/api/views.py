"""The registry's doors: the token endpoint (its realm), its push notifications, and the repositories listed."""

from __future__ import annotations

import hmac
import json

from drf_spectacular.utils import OpenApiParameter, OpenApiResponse, extend_schema
from rest_framework.exceptions import AuthenticationFailed, ParseError, ValidationError
from rest_framework.permissions import AllowAny, IsAuthenticated
from rest_framework.request import Request
from rest_framework.response import Response
from rest_framework.views import APIView

from robots.access import actor_of
from robots.models import Robot

from .. import notifications, services, tokens
from ..authentication import RegistryAuthentication
from .serializers import RegistryTokenSerializer, TokenQuerySerializer


class TokenView(APIView):
    """Answer a registry client's Basic credentials with a JWT granting what they may do of the scopes asked."""

    authentication_classes = [RegistryAuthentication]
    permission_classes = [IsAuthenticated]
    serializer_class = RegistryTokenSerializer

    @extend_schema(
        auth=[{"basicAuth": []}],
        parameters=[
            OpenApiParameter("service", str, description="The registry's service name: the token's audience."),
            OpenApiParameter(
                "scope", str, many=True, description="type:name:actions, e.g. repository:alice/hello:pull,push"
            ),
            OpenApiParameter("account", str),
            OpenApiParameter("client_id", str),
            OpenApiParameter("offline_token", str),
        ],
        responses={
            200: RegistryTokenSerializer,
            400: OpenApiResponse(description="A malformed scope or parameter"),
            401: OpenApiResponse(description="Missing or wrong credentials"),
        },
    )
    def get(self, request: Request) -> Response:
        query = TokenQuerySerializer(data=request.query_params)
        query.is_valid(raise_exception=True)
        robot = request.auth if isinstance(request.auth, Robot) else None
        try:
            answer = services.issue_token(
                actor_of(request),
                query.validated_data.get("scope", []),
                robot=robot,
                service=query.validated_data.get("service", ""),
            )
        except tokens.ScopeError as exc:
            raise ValidationError({"scope": [str(exc)]}) from None
        return Response(answer)


class RegistryEventsView(APIView):
    """Take the registry's push notifications (its ``notifications`` endpoint): the tags and their digests."""

    authentication_classes: list = []  # the registry presents the notify token, checked here
    permission_classes = [AllowAny]
    # Distribution sends application/vnd.docker.distribution.events.v1+json: read the body as it is.
    parser_classes: list = []
    # Notifications are the registry's, not a client's: their size is bounded like any request's.
    MAX_BYTES = 1 << 20

    @extend_schema(exclude=True)
    def post(self, request: Request) -> Response:
        presented = request.headers.get("Authorization", "")
        if not hmac.compare_digest(presented.encode(), f"Bearer {services.notify_token()}".encode()):
            raise AuthenticationFailed("not the registry's notify token")
        body = request.body
        if len(body) > self.MAX_BYTES:
            raise ParseError(f"a notification is at most {self.MAX_BYTES} bytes")
        try:
            envelope = json.loads(body)
        except (ValueError, UnicodeDecodeError):
            raise ParseError("a notification is a JSON envelope of events") from None
        return Response({"tags": services.record_pushes(notifications.tag_pushes(envelope))})


class RepositoriesView(APIView):
    """List the repositories of the cloud's registry a user may pull, with each tag's digest."""

    permission_classes = [IsAuthenticated]

    @extend_schema(
        parameters=[OpenApiParameter("namespace", str, description="Only this namespace (an organization's slug).")],
        responses={200: OpenApiResponse(description="[{repository, namespace, tags: [{tag, digest, size, ...}]}]")},
    )
    def get(self, request: Request) -> Response:
        namespace = request.query_params.get("namespace") or None
        return Response(services.repositories(actor_of(request), namespace))

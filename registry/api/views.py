"""The registry's token endpoint (Distribution's token authentication, its realm)."""

from __future__ import annotations

from drf_spectacular.utils import OpenApiParameter, OpenApiResponse, extend_schema
from rest_framework.exceptions import ValidationError
from rest_framework.permissions import IsAuthenticated
from rest_framework.request import Request
from rest_framework.response import Response
from rest_framework.views import APIView

from robots.models import Robot

from .. import services, tokens
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
                request.user,
                query.validated_data.get("scope", []),
                robot=robot,
                service=query.validated_data.get("service", ""),
            )
        except tokens.ScopeError as exc:
            raise ValidationError({"scope": [str(exc)]}) from None
        return Response(answer)

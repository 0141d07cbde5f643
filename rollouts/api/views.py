"""The Robot API about releases (made, listed, read; never edited) and rollouts (started, read, steered)."""

from __future__ import annotations

from django.core.exceptions import ValidationError as DjangoValidationError
from django.db.models import QuerySet
from django.shortcuts import get_object_or_404
from drf_spectacular.utils import OpenApiResponse, extend_schema
from rest_framework import generics, status
from rest_framework.exceptions import NotFound as NotFoundError
from rest_framework.exceptions import ValidationError
from rest_framework.pagination import LimitOffsetPagination
from rest_framework.request import Request
from rest_framework.response import Response
from rest_framework.views import APIView

from audit.middleware import attribute
from bridgeos_cloud.errors import NotFound
from robots.access import actor_of, require, robot_for
from robots.api.views import django_errors
from teams.roles import Right

from .. import rolling, services
from ..models import Release, Rollout, UpdateHold
from .serializers import (
    HoldCreateSerializer,
    HoldSerializer,
    ReleaseCreateSerializer,
    ReleaseQuerySerializer,
    ReleaseSerializer,
    RolloutCreateSerializer,
    RolloutDetailSerializer,
    RolloutSerializer,
)


class ReleasePagination(LimitOffsetPagination):
    # Unbounded, a huge ?limit= overflows PostgreSQL's bigint LIMIT.
    max_limit = 1000


class ReleaseListView(generics.ListAPIView):
    """Releases of your organizations, newest first (filter by organization and Skill); or make a new one."""

    serializer_class = ReleaseSerializer
    pagination_class = ReleasePagination

    @extend_schema(
        parameters=[ReleaseQuerySerializer],
        description="Releases of your organizations, newest first, filtered by organization and Skill.",
    )
    def get(self, request: Request, *args: object, **kwargs: object) -> Response:
        return super().get(request, *args, **kwargs)

    def get_queryset(self) -> QuerySet[Release]:
        if getattr(self, "swagger_fake_view", False):
            # The OpenAPI generator asks for the model only: no request, and no query (it may run before any database).
            return Release.objects.none()
        form = ReleaseQuerySerializer(data=self.request.query_params)
        form.is_valid(raise_exception=True)
        releases = services.visible_releases(actor_of(self.request))
        if "organization" in form.validated_data:
            releases = releases.filter(organization__slug=form.validated_data["organization"])
        if "skill" in form.validated_data:
            releases = releases.filter(skill_id=form.validated_data["skill"])
        return releases.order_by("-created_at", "-id")

    @extend_schema(
        description="Make the next release of a Skill (a developer's right): validated, every image pinned by digest.",
        request=ReleaseCreateSerializer,
        responses={201: ReleaseSerializer, 400: OpenApiResponse(), 403: OpenApiResponse(), 404: OpenApiResponse()},
    )
    def post(self, request: Request) -> Response:
        form = ReleaseCreateSerializer(data=request.data)
        form.is_valid(raise_exception=True)
        data = form.validated_data
        actor = actor_of(request)
        try:
            organization = services.release_organization(actor, data.get("organization"))
        except NotFound as exc:
            raise NotFoundError({exc.field or "detail": [exc.message]}) from None
        except DjangoValidationError as exc:
            raise django_errors(exc) from None
        attribute(request, organization.id, organization.slug)
        require(actor, organization.id, Right.DEVELOP)
        try:
            release = services.create_release(
                organization, data["config"], name=data["name"], notes=data["notes"], user=request.user
            )
        except DjangoValidationError as exc:
            raise django_errors(exc) from None
        return Response(ReleaseSerializer(release).data, status=status.HTTP_201_CREATED)


class ReleaseDetailView(APIView):
    """One release, as it was made: it is never edited, only superseded by the next."""

    @extend_schema(responses={200: ReleaseSerializer, 404: OpenApiResponse()})
    def get(self, request: Request, release_id: int) -> Response:
        release = get_object_or_404(services.visible_releases(actor_of(request)), pk=release_id)
        return Response(ReleaseSerializer(release).data)


class RolloutPagination(LimitOffsetPagination):
    max_limit = 1000


class RolloutListView(generics.ListAPIView):
    """Rollouts of your organizations, newest first; or start one (a developer's right)."""

    serializer_class = RolloutSerializer
    pagination_class = RolloutPagination

    def get_queryset(self) -> QuerySet[Rollout]:
        if getattr(self, "swagger_fake_view", False):
            return Rollout.objects.none()
        return rolling.visible_rollouts(actor_of(self.request))

    @extend_schema(
        description="Roll a release out to the robots a selector names: batches, soak, health gates, rollback.",
        request=RolloutCreateSerializer,
        responses={
            201: RolloutDetailSerializer,
            400: OpenApiResponse(),
            403: OpenApiResponse(),
            409: OpenApiResponse(description="A robot of the group is in another active rollout of the Skill."),
        },
    )
    def post(self, request: Request) -> Response:
        form = RolloutCreateSerializer(data=request.data)
        form.is_valid(raise_exception=True)
        data = form.validated_data
        actor = actor_of(request)
        release = services.visible_releases(actor).filter(pk=data["release"]).first()
        if release is None:
            # Unknown and another organization's release read alike: the field is what is wrong.
            raise ValidationError({"release": [f"No release {data['release']} of yours."]})
        attribute(request, release.organization_id, release.organization.slug)
        require(actor, release.organization_id, Right.DEVELOP)
        try:
            rollout = rolling.create_rollout(
                release,
                data["selector"],
                follow=data["follow"],
                strategy=data["strategy"],
                gates=data["gates"],
                user=request.user,
            )
        except DjangoValidationError as exc:
            raise django_errors(exc) from None
        except rolling.Conflict as exc:
            return Response({"detail": str(exc)}, status=status.HTTP_409_CONFLICT)
        return Response(RolloutDetailSerializer(rollout).data, status=status.HTTP_201_CREATED)


def rollout_of(request: Request, rollout_id: int) -> Rollout:
    return get_object_or_404(rolling.visible_rollouts(actor_of(request)), pk=rollout_id)


class RolloutDetailView(APIView):
    """One rollout: its state, batches, counts by status and every robot's status and reason."""

    @extend_schema(responses={200: RolloutDetailSerializer, 404: OpenApiResponse()})
    def get(self, request: Request, rollout_id: int) -> Response:
        rollout = rollout_of(request, rollout_id)
        return Response(RolloutDetailSerializer(rollout).data)


class RolloutActionView(APIView):
    """Pause, resume or abort a rollout (a developer's right); an abort rolls back every robot it touched."""

    action_name = ""

    @extend_schema(
        request=None,
        responses={200: RolloutSerializer, 403: OpenApiResponse(), 404: OpenApiResponse(), 409: OpenApiResponse()},
    )
    def post(self, request: Request, rollout_id: int) -> Response:
        rollout = rollout_of(request, rollout_id)
        require(actor_of(request), rollout.organization_id, Right.DEVELOP)
        try:
            rollout = rolling.steer(rollout, self.action_name, request.user.get_username() or "a token")
        except rolling.Conflict as exc:
            return Response({"detail": str(exc)}, status=status.HTTP_409_CONFLICT)
        return Response(RolloutSerializer(rollout).data)


class HoldView(APIView):
    """A robot's update hold: rollouts defer it (download, no install) until released or past its deadline."""

    @extend_schema(responses={200: HoldSerializer, 404: OpenApiResponse()})
    def get(self, request: Request, robot_id: str) -> Response:
        robot = robot_for(actor_of(request), robot_id)
        hold = UpdateHold.objects.filter(robot=robot).first()
        return Response({"robot": robot.id, "hold": HoldSerializer(hold).data if hold is not None else None})

    @extend_schema(request=HoldCreateSerializer, responses={200: HoldSerializer, 400: OpenApiResponse()})
    def post(self, request: Request, robot_id: str) -> Response:
        robot = robot_for(actor_of(request), robot_id, Right.COMMAND)
        form = HoldCreateSerializer(data=request.data)
        form.is_valid(raise_exception=True)
        holder = f"owner {request.user.get_username()}"
        try:
            hold = rolling.hold_updates(robot, holder, form.validated_data["seconds"], form.validated_data["reason"])
        except DjangoValidationError as exc:
            raise django_errors(exc) from None
        return Response({"robot": robot.id, "hold": HoldSerializer(hold).data})

    @extend_schema(request=None, responses={204: None, 404: OpenApiResponse()})
    def delete(self, request: Request, robot_id: str) -> Response:
        """Release the hold (none held: nothing to do, the same answer)."""
        robot = robot_for(actor_of(request), robot_id, Right.COMMAND)
        rolling.release_hold(robot, f"owner {request.user.get_username()}")
        return Response(status=status.HTTP_204_NO_CONTENT)

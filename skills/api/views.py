"""The Robot API about skills, components and the catalog (thesis Table 3.1)."""

from __future__ import annotations

from django.core.exceptions import ValidationError as DjangoValidationError
from django.db.models import QuerySet
from django.http import Http404, HttpResponse
from django.shortcuts import get_object_or_404
from drf_spectacular.utils import OpenApiResponse, extend_schema
from rest_framework import status
from rest_framework.exceptions import PermissionDenied, ValidationError
from rest_framework.request import Request
from rest_framework.response import Response
from rest_framework.views import APIView

from bridgeos_agent.protocol import Event
from robots.access import actor_of, require, visible_robots
from robots.api.commands import relay, wait_seconds
from robots.api.views import COMMAND_RESPONSES, WAIT, django_errors, robot_of
from teams.models import Organization
from teams.roles import Right

from .. import services, state
from ..cloud.volumes import volume_quota, volume_usage
from ..models import Component, Skill, SkillTemplate
from .serializers import (
    ComponentDetailSerializer,
    ComponentMigrateSerializer,
    ComponentStartSerializer,
    ComponentStopSerializer,
    SkillAddSerializer,
    SkillDetailSerializer,
    SkillRemoveSerializer,
    SkillTemplateSerializer,
    VolumeUsageSerializer,
)


def skill_of(request: Request, robot_id: str, skill_id: str, right: Right = Right.READ) -> Skill:
    """Return a skill of a robot the request holds a right on, or 404 (403 when its role falls short)."""
    robot = robot_of(request, robot_id, right)
    return get_object_or_404(Skill.objects.prefetch_related("components"), robot=robot, skill_id=skill_id)


def component_of(
    request: Request, robot_id: str, skill_id: str, component_id: str, right: Right = Right.READ
) -> Component:
    """Return a component of a skill of a robot the request holds a right on, or 404 (403)."""
    skill = skill_of(request, robot_id, skill_id, right)
    return get_object_or_404(Component.objects.select_related("skill"), skill=skill, component_id=component_id)


def validated(serializer_class: type, request: Request) -> dict:
    form = serializer_class(data=request.data)
    form.is_valid(raise_exception=True)
    return form.validated_data


class SkillAddView(APIView):
    """Add a Skill to a robot, from a config or a catalog template."""

    @extend_schema(request=SkillAddSerializer, responses={201: SkillDetailSerializer, 400: OpenApiResponse()})
    def post(self, request: Request, robot_id: str) -> Response:
        robot = robot_of(request, robot_id, Right.DEVELOP)
        data = validated(SkillAddSerializer, request)
        template = data.get("template")
        if template is not None and template.organization_id not in (None, robot.organization_id):
            # Another organization's template is as unknown here as one that does not exist.
            raise ValidationError({"template": [f'Invalid pk "{template.pk}" - object does not exist.']})
        config = template.config if template is not None else data["config"]
        if not isinstance(config, dict):
            raise ValidationError({"config": ["A Skill config is a JSON object."]})
        try:
            skill = services.add_skill(robot, config)
        except DjangoValidationError as exc:
            raise django_errors(exc) from None
        return Response(SkillDetailSerializer(skill_of(request, robot_id, skill.skill_id)).data, status=201)


class SkillRemoveView(APIView):
    """Remove a stopped Skill from a robot."""

    @extend_schema(
        request=SkillRemoveSerializer,
        responses={204: OpenApiResponse(description="Removed"), 404: OpenApiResponse(), 409: OpenApiResponse()},
    )
    def post(self, request: Request, robot_id: str) -> Response:
        robot_of(request, robot_id, Right.DEVELOP)
        skill = skill_of(request, robot_id, validated(SkillRemoveSerializer, request)["skill"])
        if not services.remove_skill(skill):
            return Response(
                {"detail": f"Skill {skill.skill_id} is {skill.status}; stop it before removing it."},
                status=status.HTTP_409_CONFLICT,
            )
        return Response(status=status.HTTP_204_NO_CONTENT)


class RobotVolumesView(APIView):
    """What a robot's Skill volumes hold in the cloud, and its volume quota."""

    @extend_schema(responses={200: VolumeUsageSerializer, 404: OpenApiResponse()})
    def get(self, request: Request, robot_id: str) -> Response:
        robot = robot_of(request, robot_id)
        usage = volume_usage(robot.id)
        return Response({"quota_bytes": volume_quota(), "used_bytes": sum(usage.values()), "volumes": usage})


class SkillInfoView(APIView):
    """The current state of a Skill, its config and components."""

    @extend_schema(responses={200: SkillDetailSerializer, 404: OpenApiResponse()})
    def get(self, request: Request, robot_id: str, skill_id: str) -> HttpResponse:
        text = state.skill_state_json(visible_robots(actor_of(request)), robot_id, skill_id)
        if text is None:
            raise Http404("No such skill.")
        return HttpResponse(text, content_type="application/json")


class SkillStartView(APIView):
    """Launch a Skill on its robot."""

    @extend_schema(request=None, parameters=[WAIT], responses=COMMAND_RESPONSES)
    def post(self, request: Request, robot_id: str, skill_id: str) -> Response:
        skill = skill_of(request, robot_id, skill_id, Right.COMMAND)
        return relay(robot_id, Event.SKILL_START, services.start_order(skill), wait_seconds(request))


class SkillStopView(APIView):
    """Shut a Skill down."""

    @extend_schema(request=None, parameters=[WAIT], responses=COMMAND_RESPONSES)
    def post(self, request: Request, robot_id: str, skill_id: str) -> Response:
        skill = skill_of(request, robot_id, skill_id, Right.COMMAND)
        return relay(robot_id, Event.SKILL_STOP, {"skill": skill.skill_id}, wait_seconds(request))


class ComponentInfoView(APIView):
    """A component: where it may and does run, its status and containers."""

    @extend_schema(responses={200: ComponentDetailSerializer, 404: OpenApiResponse()})
    def get(self, request: Request, robot_id: str, skill_id: str, component_id: str) -> HttpResponse:
        text = state.component_state_json(visible_robots(actor_of(request)), robot_id, skill_id, component_id)
        if text is None:
            raise Http404("No such component.")
        return HttpResponse(text, content_type="application/json")


class ComponentStartView(APIView):
    """Start a component at the requested location."""

    @extend_schema(request=ComponentStartSerializer, parameters=[WAIT], responses=COMMAND_RESPONSES)
    def post(self, request: Request, robot_id: str, skill_id: str, component_id: str) -> Response:
        component = component_of(request, robot_id, skill_id, component_id, Right.COMMAND)
        location = validated(ComponentStartSerializer, request)["location"]
        try:
            services.check_location(component, location)
        except DjangoValidationError as exc:
            raise django_errors(exc) from None
        data = {"skill": skill_id, "component": component_id, "location": location}
        return relay(robot_id, Event.COMPONENT_START, data, wait_seconds(request))


class ComponentStopView(APIView):
    """Stop a component (at one location, or wherever it runs)."""

    @extend_schema(request=ComponentStopSerializer, parameters=[WAIT], responses=COMMAND_RESPONSES)
    def post(self, request: Request, robot_id: str, skill_id: str, component_id: str) -> Response:
        component_of(request, robot_id, skill_id, component_id, Right.COMMAND)
        data = {"skill": skill_id, "component": component_id, **validated(ComponentStopSerializer, request)}
        return relay(robot_id, Event.COMPONENT_STOP, data, wait_seconds(request))


class ComponentMigrateView(APIView):
    """Move a component to the other side (or the given one)."""

    @extend_schema(request=ComponentMigrateSerializer, parameters=[WAIT], responses=COMMAND_RESPONSES)
    def post(self, request: Request, robot_id: str, skill_id: str, component_id: str) -> Response:
        component = component_of(request, robot_id, skill_id, component_id, Right.COMMAND)
        try:
            target = services.migration_target(
                component, validated(ComponentMigrateSerializer, request).get("location")
            )
        except DjangoValidationError as exc:
            raise django_errors(exc) from None
        data = {"skill": skill_id, "component": component_id, "location": target}
        return relay(robot_id, Event.COMPONENT_MIGRATE, data, wait_seconds(request))


def visible_templates(request: Request) -> QuerySet[SkillTemplate]:
    """Return the cloud's catalog and the templates of the organizations a request reaches."""
    return services.visible_templates(actor_of(request))


def may_keep(request: Request, organization_id: int | None) -> None:
    """Raise a 403 unless the request may change templates there: a developer's right, the catalog staff's."""
    if organization_id is None:
        if not (request.user.is_staff and actor_of(request).everywhere):
            raise PermissionDenied("Only staff keep the cloud's catalog; name an organization of yours.")
    else:
        require(actor_of(request), organization_id, Right.DEVELOP)


class SkillTemplateListView(APIView):
    """Skill templates: the cloud's catalog and your organizations'; list them, or upload a config as a new one."""

    @extend_schema(responses={200: SkillTemplateSerializer(many=True)})
    def get(self, request: Request) -> Response:
        return Response(SkillTemplateSerializer(visible_templates(request).order_by("name"), many=True).data)

    @extend_schema(
        request=SkillTemplateSerializer,
        responses={201: SkillTemplateSerializer, 400: OpenApiResponse(), 403: OpenApiResponse()},
    )
    def post(self, request: Request) -> Response:
        form = SkillTemplateSerializer(data=request.data)
        form.is_valid(raise_exception=True)
        data = dict(form.validated_data)
        slug = (data.pop("organization", None) or {}).get("slug")
        organization = None
        if slug is not None:
            ids = actor_of(request).organization_ids()
            found = Organization.objects.filter(slug=slug)
            organization = (found if ids is None else found.filter(id__in=ids)).first()
            if organization is None:
                raise ValidationError({"organization": ["No such organization of yours."]})
        may_keep(request, organization.id if organization else None)
        try:
            template = services.create_template(**data, organization=organization)
        except DjangoValidationError as exc:
            raise django_errors(exc) from None
        return Response(SkillTemplateSerializer(template).data, status=status.HTTP_201_CREATED)


class SkillTemplateDetailView(APIView):
    """One template; a developer of its organization (staff, for the catalog) may delete it."""

    @extend_schema(responses={200: SkillTemplateSerializer, 404: OpenApiResponse()})
    def get(self, request: Request, template_id: int) -> Response:
        return Response(SkillTemplateSerializer(get_object_or_404(visible_templates(request), pk=template_id)).data)

    @extend_schema(
        responses={204: OpenApiResponse(description="Deleted"), 403: OpenApiResponse(), 404: OpenApiResponse()}
    )
    def delete(self, request: Request, template_id: int) -> Response:
        template = get_object_or_404(visible_templates(request), pk=template_id)
        may_keep(request, template.organization_id)
        template.delete()
        return Response(status=status.HTTP_204_NO_CONTENT)

"""The Robot API about robots: authentication, the fleet, and robot-wide commands (thesis Table 3.1)."""

from __future__ import annotations

import json
from typing import Any

from django.contrib.auth import get_user_model
from django.core.exceptions import ValidationError as DjangoValidationError
from django.db.models import QuerySet
from django.http import Http404, HttpResponse
from drf_spectacular.utils import OpenApiParameter, OpenApiResponse, extend_schema
from rest_framework import status
from rest_framework.authentication import SessionAuthentication
from rest_framework.exceptions import PermissionDenied, ValidationError
from rest_framework.permissions import IsAuthenticated
from rest_framework.request import Request
from rest_framework.response import Response
from rest_framework.utils.urls import replace_query_param
from rest_framework.views import APIView

from bridgeos_agent.protocol import Event
from monitoring.services import record_event
from skills.state import fleet_fields_json, fleet_state_json
from teams.models import Organization
from teams.roles import Right
from teams.services import personal_organization

from .. import access, rotation, services
from ..authentication import ApiTokenAuthentication, PasswordAuthentication
from ..labels import selector_q
from ..models import ApiToken, Robot
from .commands import relay, relay_to_fleet, wait_seconds
from .serializers import (
    AuthTokenSerializer,
    BridgeTicketSerializer,
    CommandResultSerializer,
    FleetCommandSerializer,
    FleetQuerySerializer,
    RenewedTokenSerializer,
    RobotCreatedSerializer,
    RobotCreateSerializer,
    RobotSerializer,
    RobotTokenRotateSerializer,
    RobotTokenSerializer,
    RobotUpdateSerializer,
)

WAIT = OpenApiParameter("wait", float, description="Seconds to wait for the robot's reply (default 5, max 60).")
COMMAND_RESPONSES = {
    200: CommandResultSerializer,
    400: OpenApiResponse(description="Invalid request"),
    404: OpenApiResponse(description="No such robot, skill or component (or not yours)"),
    409: OpenApiResponse(description="The robot is offline"),
    504: OpenApiResponse(description="The robot did not answer in time"),
}


def django_errors(exc: DjangoValidationError) -> ValidationError:
    """Turn a model's field errors into a DRF 400."""
    return ValidationError(getattr(exc, "message_dict", {"non_field_errors": exc.messages}))


def state_of(request: Request, robot_id: str) -> dict:
    """Return the state of one of the user's robots, or 404, as every robot route renders it."""
    found = json.loads(fleet_state_json(access.visible_robots(access.actor_of(request)).filter(id=robot_id)))
    if not found:
        raise Http404(f"No robot {robot_id!r}.")
    return found[0]


def json_state(request: Request, robots: QuerySet[Robot], *, one: bool = False) -> HttpResponse:
    """Answer with robots' state as JSON built by the database (one robot, or 404, when ``one``)."""
    text = fleet_state_json(robots)
    if one:
        if text == "[]":
            raise Http404("No such robot.")
        # The array holds exactly one robot: answer with the object inside it.
        text = text[1:-1]
    return HttpResponse(text, content_type="application/json")


DEFAULT_PAGE = 100


def fleet_page(request: Request, robots: QuerySet[Robot], query: dict) -> HttpResponse:
    """Answer with one page of robots in id order: their count, the next and previous page's URLs, the page."""
    offset, limit = query.get("offset", 0), query.get("limit", DEFAULT_PAGE)
    count = robots.count()
    page = robots.order_by("id")[offset : offset + limit]
    text = fleet_fields_json(page, query["fields"]) if "fields" in query else fleet_state_json(page)
    url = request.build_absolute_uri()
    following = replace_query_param(url, "offset", offset + limit) if offset + limit < count else None
    previous = replace_query_param(url, "offset", max(0, offset - limit)) if offset > 0 else None
    head = json.dumps({"count": count, "next": following, "previous": previous})[:-1]
    return HttpResponse(f'{head}, "results": {text}}}', content_type="application/json")


def robot_of(request: Request, robot_id: str, right: Right = Right.READ) -> Robot:
    """Return a robot the request holds a right on; another organization's is a 404, as if it did not exist."""
    return access.robot_for(access.actor_of(request), robot_id, right)


def target_organization(request: Request, slug: str | None, owner: Any) -> Organization:
    """Return the organization a new robot goes to, where the request must be an admin; 400/403 when not.

    Named, it must be one the request reaches (another's is as unknown as a missing one); not
    named, it is the scoped token's or the session's, else the owner's personal organization.
    """
    actor = access.actor_of(request)
    if slug is not None:
        ids = actor.organization_ids()
        found = Organization.objects.filter(slug=slug)
        organization = (found if ids is None else found.filter(id__in=ids)).first()
        if organization is None:
            raise ValidationError({"organization": ["No such organization of yours."]})
    elif actor.organization_id is not None:
        organization = Organization.objects.get(id=actor.organization_id)
    else:
        organization = personal_organization(owner)
    access.require(actor, organization.id, Right.ADMINISTER)
    return organization


class AuthView(APIView):
    """Exchange a username and password (HTTP Basic) for an API token with an expiry."""

    authentication_classes = [PasswordAuthentication, SessionAuthentication]
    permission_classes = [IsAuthenticated]
    serializer_class = AuthTokenSerializer

    @extend_schema(auth=[{"basicAuth": []}], responses={200: AuthTokenSerializer, 401: OpenApiResponse()})
    def get(self, request: Request) -> Response:
        key, token = services.issue_api_token(request.user)
        user = request.user.get_username()
        record_event(f"API token issued to user {user}", kind="api_token_issued", data={"user": user})
        return Response({"token": key, "expires_at": token.expires_at})

    @extend_schema(auth=[{"basicAuth": []}], responses={200: AuthTokenSerializer, 401: OpenApiResponse()})
    def post(self, request: Request) -> Response:
        return self.get(request)


class AuthRenewView(APIView):
    """Extend the validity of the API token this request carries."""

    authentication_classes = [ApiTokenAuthentication]
    serializer_class = RenewedTokenSerializer

    @extend_schema(responses={200: RenewedTokenSerializer, 401: OpenApiResponse()})
    def get(self, request: Request) -> Response:
        if not isinstance(request.auth, ApiToken):
            raise PermissionDenied("Only an API token can be renewed.")
        return Response({"expires_at": services.renew_api_token(request.auth).expires_at})

    @extend_schema(responses={200: RenewedTokenSerializer, 401: OpenApiResponse()})
    def post(self, request: Request) -> Response:
        return self.get(request)


class RobotListView(APIView):
    """List the robots you may see with their skills and components, or add a robot."""

    @extend_schema(
        parameters=[
            OpenApiParameter("connected", bool, description="Only connected (true) or offline (false)."),
            FleetQuerySerializer,
        ],
        responses={200: RobotSerializer(many=True)},
        description="Without `limit`/`offset` the answer is the array of every robot; with either, a page: "
        "`{count, next, previous, results}`. `fields` keeps only those fields of each robot; `selector` keeps only "
        "the robots whose labels match it (400 naming `selector` when it is malformed).",
    )
    def get(self, request: Request) -> HttpResponse:
        robots = access.visible_robots(access.actor_of(request))
        connected = request.query_params.get("connected")
        if connected is not None:
            if connected not in ("true", "false"):
                raise ValidationError({"connected": ["Use true or false."]})
            robots = robots.filter(connected=connected == "true")
        form = FleetQuerySerializer(data=request.query_params)
        form.is_valid(raise_exception=True)
        query = form.validated_data
        if "selector" in query:
            robots = robots.filter(selector_q(query["selector"]))
        if "limit" not in query and "offset" not in query:
            if "fields" in query:
                return HttpResponse(fleet_fields_json(robots, query["fields"]), content_type="application/json")
            return json_state(request, robots)
        return fleet_page(request, robots, query)

    @extend_schema(request=RobotCreateSerializer, responses={201: RobotCreatedSerializer, 400: OpenApiResponse()})
    def post(self, request: Request) -> Response:
        form = RobotCreateSerializer(data=request.data)
        form.is_valid(raise_exception=True)
        owner = request.user
        if "owner" in form.validated_data and form.validated_data["owner"] != request.user.get_username():
            if not request.user.is_staff:
                raise PermissionDenied("Only staff may create robots for another user.")
            owner = get_user_model().objects.filter(username=form.validated_data["owner"]).first()
            if owner is None:
                raise ValidationError({"owner": ["No such user."]})
        organization = target_organization(request, form.validated_data.get("organization"), owner)
        if Robot.objects.filter(id=form.validated_data["id"]).exists():
            raise ValidationError({"id": ["A robot with this id exists already."]})
        try:
            robot, token = services.create_robot(
                form.validated_data["id"],
                owner,
                name=form.validated_data["name"],
                config=form.validated_data.get("config"),
                organization=organization,
                labels=form.validated_data.get("labels"),
            )
        except DjangoValidationError as exc:
            raise django_errors(exc) from None
        return Response({**state_of(request, robot.id), "token": token}, status=status.HTTP_201_CREATED)


class RobotDetailView(APIView):
    """Read, rename, reconfigure or relabel, or delete one robot."""

    @extend_schema(responses={200: RobotSerializer, 404: OpenApiResponse()})
    def get(self, request: Request, robot_id: str) -> HttpResponse:
        return json_state(request, access.visible_robots(access.actor_of(request)).filter(id=robot_id), one=True)

    @extend_schema(request=RobotUpdateSerializer, responses={200: RobotSerializer, 400: OpenApiResponse()})
    def patch(self, request: Request, robot_id: str) -> Response:
        robot = robot_of(request, robot_id, Right.ADMINISTER)
        form = RobotUpdateSerializer(data=request.data)
        form.is_valid(raise_exception=True)
        try:
            services.update_robot(robot, **form.validated_data)
        except DjangoValidationError as exc:
            raise django_errors(exc) from None
        return Response(state_of(request, robot_id))

    @extend_schema(responses={204: OpenApiResponse(description="Deleted"), 404: OpenApiResponse()})
    def delete(self, request: Request, robot_id: str) -> Response:
        services.delete_robot(robot_of(request, robot_id, Right.ADMINISTER))
        return Response(status=status.HTTP_204_NO_CONTENT)


class RobotInfoView(APIView):
    """Everything about the current state of a robot, its skills and components."""

    @extend_schema(responses={200: RobotSerializer, 404: OpenApiResponse()})
    def get(self, request: Request, robot_id: str) -> HttpResponse:
        return json_state(request, access.visible_robots(access.actor_of(request)).filter(id=robot_id), one=True)


class RobotTokenView(APIView):
    """Rotate a robot's token: the new one works at once; the old one for `grace_s` seconds (default: not at all)."""

    @extend_schema(
        request=RobotTokenRotateSerializer,
        responses={200: RobotTokenSerializer, 403: OpenApiResponse(), 404: OpenApiResponse()},
    )
    def post(self, request: Request, robot_id: str) -> Response:
        robot = robot_of(request, robot_id, Right.ADMINISTER)
        form = RobotTokenRotateSerializer(data=request.data)
        form.is_valid(raise_exception=True)
        token = rotation.rotate_token(robot, grace_s=form.validated_data["grace_s"])
        return Response({"token": token, "old_token_valid_until": robot.previous_token_until})


class BridgeTicketView(APIView):
    """Get a ticket for one of your robot's bridges: for browsers, which cannot send an Authorization header."""

    @extend_schema(request=None, responses={200: BridgeTicketSerializer, 404: OpenApiResponse()})
    def post(self, request: Request, robot_id: str) -> Response:
        robot = robot_of(request, robot_id, Right.COMMAND)
        ticket, expires_at = services.issue_bridge_ticket(request.user, robot)
        base = request.build_absolute_uri("/").replace("http", "ws", 1).rstrip("/")
        return Response(
            {
                "ticket": ticket,
                "expires_at": expires_at,
                "rosbridge_url": f"{base}/ws/rosbridge/{robot.id}/?ticket={ticket}",
                "foxglove_url": f"{base}/ws/foxglove/{robot.id}/?ticket={ticket}",
            }
        )


class RobotCommandView(APIView):
    """Relay start, stop or shutdown to one robot."""

    event = Event.ROBOT_START  # each route sets its own

    @extend_schema(request=None, parameters=[WAIT], responses=COMMAND_RESPONSES)
    def post(self, request: Request, robot_id: str) -> Response:
        robot = robot_of(request, robot_id, Right.COMMAND)
        return relay(robot.id, self.event, {}, wait_seconds(request))


class FleetCommandView(APIView):
    """Relay start, stop or shutdown to every connected robot you may command."""

    event = Event.ROBOT_START  # each route sets its own

    @extend_schema(request=None, parameters=[WAIT], responses={200: FleetCommandSerializer})
    def post(self, request: Request) -> Response:
        wait = wait_seconds(request)
        robot_ids = list(
            access.robots_with(access.actor_of(request), Right.COMMAND)
            .filter(connected=True)
            .values_list("id", flat=True)
        )
        return relay_to_fleet(robot_ids, self.event, wait)

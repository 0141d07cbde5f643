"""The Robot API about recordings: start, stop, list, download and delete a robot's MCAP recordings."""

from __future__ import annotations

from collections.abc import Callable
from typing import TypeVar
from uuid import UUID

from django.http import FileResponse, Http404
from django.shortcuts import get_object_or_404
from drf_spectacular.utils import OpenApiParameter, OpenApiResponse, extend_schema
from rest_framework import status
from rest_framework.exceptions import ValidationError
from rest_framework.request import Request
from rest_framework.response import Response
from rest_framework.views import APIView

from robots import services as robots
from robots.api.commands import wait_seconds
from robots.api.views import WAIT, robot_of
from teams.roles import Right

from .. import services
from ..models import Recording
from .serializers import RecordingSerializer, RecordingStartSerializer

T = TypeVar("T")

MAX_LIMIT = 1000
LIMIT = OpenApiParameter("limit", int, description=f"Only the newest N recordings (1 to {MAX_LIMIT}).")


def list_limit(request: Request) -> int | None:
    """Read `?limit=` (the newest N recordings), or None for all."""
    raw = request.query_params.get("limit")
    if raw is None:
        return None
    if not raw.isdigit() or not 1 <= int(raw) <= MAX_LIMIT:
        raise ValidationError({"limit": [f"A whole number from 1 to {MAX_LIMIT}."]})
    return int(raw)


REFUSALS = {
    400: OpenApiResponse(description="Invalid request (unknown topic, limits out of range, one running already)"),
    404: OpenApiResponse(description="No such robot or recording (or not yours)"),
    409: OpenApiResponse(description="The robot is offline"),
    504: OpenApiResponse(description="The robot did not answer in time"),
}


def recording_of(request: Request, robot_id: str, recording_id: str, right: Right = Right.READ) -> Recording:
    """Return a recording (named by its 32 hex digits) of a robot the request holds a right on; else 404 (403)."""
    robot = robot_of(request, robot_id, right)
    try:
        key = UUID(hex=recording_id)
    except ValueError:
        raise Http404(f"No recording {recording_id!r}.") from None
    return get_object_or_404(services.recordings_of(robot), id=key)


def on_robot(action: Callable[[], T], robot_id: str) -> T | Response:
    """Run an action that orders the robot; answer its refusals as 400, 409 or 504."""
    try:
        return action()
    except services.RecordingRefused as exc:
        raise ValidationError({exc.field: [exc.message]}) from None
    except robots.RobotOffline:
        return Response(
            {"detail": f"Robot {robot_id} is offline; connect it and try again."}, status=status.HTTP_409_CONFLICT
        )
    except robots.CommandTimeout as exc:
        return Response({"detail": str(exc)}, status=status.HTTP_504_GATEWAY_TIMEOUT)


class RecordingListView(APIView):
    """List a robot's recordings, or start one."""

    @extend_schema(
        parameters=[LIMIT],
        responses={200: RecordingSerializer(many=True), 400: OpenApiResponse(), 404: OpenApiResponse()},
    )
    def get(self, request: Request, robot_id: str) -> Response:
        recordings = services.recordings_of(robot_of(request, robot_id))
        limit = list_limit(request)
        if limit is not None:
            recordings = recordings[:limit]
        return Response(RecordingSerializer(recordings, many=True, context={"request": request}).data)

    @extend_schema(
        request=RecordingStartSerializer, parameters=[WAIT], responses={201: RecordingSerializer, **REFUSALS}
    )
    def post(self, request: Request, robot_id: str) -> Response:
        robot = robot_of(request, robot_id, Right.COMMAND)
        form = RecordingStartSerializer(data=request.data)
        form.is_valid(raise_exception=True)
        wait = wait_seconds(request)
        started = on_robot(lambda: services.start_recording(robot, wait=wait, **form.validated_data), robot.id)
        if isinstance(started, Response):
            return started
        data = RecordingSerializer(started, context={"request": request}).data
        return Response(data, status=status.HTTP_201_CREATED)


class RecordingDetailView(APIView):
    """Read or delete one recording."""

    @extend_schema(responses={200: RecordingSerializer, 404: OpenApiResponse()})
    def get(self, request: Request, robot_id: str, recording_id: str) -> Response:
        recording = recording_of(request, robot_id, recording_id)
        return Response(RecordingSerializer(recording, context={"request": request}).data)

    @extend_schema(responses={204: OpenApiResponse(description="Deleted"), **REFUSALS})
    def delete(self, request: Request, robot_id: str, recording_id: str) -> Response:
        recording = recording_of(request, robot_id, recording_id, Right.COMMAND)
        on_robot(lambda: services.delete_recording(recording), robot_id)
        return Response(status=status.HTTP_204_NO_CONTENT)


class RecordingStopView(APIView):
    """End a running recording; the robot sends its last chunks and the file is assembled."""

    @extend_schema(request=None, parameters=[WAIT], responses={200: RecordingSerializer, **REFUSALS})
    def post(self, request: Request, robot_id: str, recording_id: str) -> Response:
        recording = recording_of(request, robot_id, recording_id, Right.COMMAND)
        wait = wait_seconds(request)
        stopped = on_robot(lambda: services.stop_recording(recording, wait=wait), robot_id)
        if isinstance(stopped, Response):
            return stopped
        return Response(RecordingSerializer(stopped, context={"request": request}).data)


class RecordingDownloadView(APIView):
    """Download a finished recording's .mcap file."""

    @extend_schema(
        responses={
            (200, "application/octet-stream"): OpenApiResponse(description="The MCAP file"),
            404: OpenApiResponse(),
            409: OpenApiResponse(description="Not assembled yet"),
        }
    )
    def get(self, request: Request, robot_id: str, recording_id: str) -> FileResponse | Response:
        recording = recording_of(request, robot_id, recording_id)
        path = recording.path
        if path is None:
            return Response(
                {"detail": f"Recording {recording.id} is {recording.status}: its file is not assembled yet."},
                status=status.HTTP_409_CONFLICT,
            )
        if not path.is_file():
            raise Http404("The recording's file is gone.")
        return FileResponse(
            path.open("rb"),
            as_attachment=True,
            filename=f"{recording.robot_id}-{recording.id.hex}.mcap",
            content_type="application/octet-stream",
        )

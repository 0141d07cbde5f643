"""The dashboard's pages: each renders its first state; the page's script keeps it live."""

from __future__ import annotations

import json

from django.conf import settings
from django.contrib.auth.decorators import login_required
from django.http import Http404, HttpRequest, HttpResponse, JsonResponse
from django.shortcuts import render
from django.views.decorators.http import require_POST

from bridgeos_agent.errors import NON_FIELD
from monitoring.choices import Level
from registry import services as registry_services

from . import services


@login_required
def fleet(request: HttpRequest) -> HttpResponse:
    """Show every robot the user may see, live."""
    return render(
        request,
        "dashboard/fleet.html",
        {"page": "fleet", "robots": services.fleet_summary(request.user), "metric_names": services.ROBOT_METRICS},
    )


@login_required
def robot(request: HttpRequest, robot_id: str) -> HttpResponse:
    """Show one robot: skills, components, commands, charts, decisions and its config."""
    state = services.robot_state(request.user, robot_id)
    if state is None:
        raise Http404("No such robot.")
    return render(
        request,
        "dashboard/robot.html",
        {
            "page": "fleet",
            "robot": state,
            "choices": services.robot_config_choices(),
            "recordings": services.robot_recordings(robot_id),
            "recording_limits": services.recording_limits(),
        },
    )


@login_required
def skills(request: HttpRequest) -> HttpResponse:
    """Show the Skill catalog, and take an uploaded Skill config."""
    return render(
        request,
        "dashboard/skills.html",
        {"page": "skills", "templates": services.catalog(), "robots": services.robot_choices(request.user)},
    )


@login_required
def images(request: HttpRequest) -> HttpResponse:
    """Show the images of the cloud's registry the user may pull, each tag with its digest, and how to push."""
    return render(
        request,
        "dashboard/images.html",
        {
            "page": "images",
            "repositories": registry_services.repositories(request.user),
            "registry": settings.BRIDGEOS["REGISTRY_HOST"],
            "namespace": request.user.get_username(),
        },
    )


@login_required
def events(request: HttpRequest) -> HttpResponse:
    """Show the event log, filtered, with a live tail."""
    skill_ids, component_ids = services.skill_and_component_ids(request.user)
    return render(
        request,
        "dashboard/events.html",
        {
            "page": "events",
            "robots": services.robot_choices(request.user),
            "levels": Level.choices,
            "skill_ids": skill_ids,
            "component_ids": component_ids,
            "filters": {key: request.GET.get(key, "") for key in ("robot", "skill", "component", "level")},
        },
    )


@login_required
@require_POST
def validate_config(request: HttpRequest, kind: str) -> JsonResponse:
    """Check a Skill or robot config against the shared schema; answer its field errors.

    An invalid config is a successful check (200 with ``valid: false``), not a failed request.
    """
    try:
        data = json.loads(request.body)
    except ValueError as exc:
        return JsonResponse({"valid": False, "errors": {NON_FIELD: [f"not JSON: {exc}"]}}, status=400)
    config, errors = services.validate_config(kind, data)
    if errors:
        return JsonResponse({"valid": False, "errors": errors})
    return JsonResponse({"valid": True, "config": config})

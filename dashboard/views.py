"""The dashboard's pages: each renders its first state; the page's script keeps it live."""

from __future__ import annotations

import json
from typing import get_args

from django.conf import settings
from django.contrib.auth.decorators import login_required
from django.http import Http404, HttpRequest, HttpResponse, JsonResponse
from django.shortcuts import render
from django.views.decorators.http import require_POST

from bridgeos_agent.errors import NON_FIELD
from bridgeos_agent.protocol import LogLevel
from monitoring.choices import Level
from registry import services as registry_services
from robots.access import actor_of

from . import services
from .forms import FleetQueryForm

# The levels a log line may carry, lowest first: the viewer's "level at least" picker.
LOG_LEVELS = get_args(LogLevel)


@login_required
def fleet(request: HttpRequest) -> HttpResponse:
    """Show one page of the robots the user may see, searched and sorted as the address asks, live."""
    fleet_page = services.fleet_page(actor_of(request), FleetQueryForm(request.GET).query())
    return render(request, "dashboard/fleet.html", {"page": "fleet", "fleet": fleet_page})


@login_required
def fleet_data(request: HttpRequest) -> JsonResponse:
    """Answer a page of the fleet as the fleet page redraws it in place (search, sort, paging, live counts)."""
    form = FleetQueryForm(request.GET)
    if not form.is_valid():
        return JsonResponse({field: list(messages) for field, messages in form.errors.items()}, status=400)
    return JsonResponse(services.fleet_page(actor_of(request), form.query()))


@login_required
def robot(request: HttpRequest, robot_id: str) -> HttpResponse:
    """Show one robot: skills, components, commands, charts, decisions and its config."""
    state = services.robot_state(actor_of(request), robot_id)
    if state is None:
        raise Http404("No such robot.")
    rights = services.robot_rights(actor_of(request), robot_id)
    return render(
        request,
        "dashboard/robot.html",
        {
            "page": "fleet",
            "robot": state,
            "rights": rights,
            "can_command": rights["command"],
            "can_develop": rights["develop"],
            "can_administer": rights["administer"],
            "choices": services.robot_config_choices(),
            "recordings": services.robot_recordings(robot_id),
            "recording_limits": services.recording_limits(),
            "log_levels": LOG_LEVELS,
        },
    )


@login_required
def robot_logs(request: HttpRequest, robot_id: str) -> HttpResponse:
    """Show one robot's log viewer, filtered by the address (a component's logs: ?skill=..&component=..)."""
    state = services.robot_state(actor_of(request), robot_id)
    if state is None:
        raise Http404("No such robot.")
    return render(
        request, "dashboard/logs.html", {"page": "fleet", "robot": state, "full": True, "log_levels": LOG_LEVELS}
    )


@login_required
def skills(request: HttpRequest) -> HttpResponse:
    """Show the Skill catalog, and take an uploaded Skill config."""
    actor = actor_of(request)
    return render(
        request,
        "dashboard/skills.html",
        {
            "page": "skills",
            "templates": services.catalog(actor),
            "robots": services.robots_to_develop(actor),
            "template_organizations": services.template_organizations(actor),
        },
    )


@login_required
def images(request: HttpRequest) -> HttpResponse:
    """Show the images of the cloud's registry the user may pull, each tag with its digest, and how to push."""
    actor = actor_of(request)
    namespaces = services.namespaces(actor)
    return render(
        request,
        "dashboard/images.html",
        {
            "page": "images",
            "repositories": registry_services.repositories(actor),
            "registry": settings.BRIDGEOS["REGISTRY_HOST"],
            "namespace": namespaces[0] if namespaces else request.user.get_username(),
            "namespaces": namespaces,
        },
    )


@login_required
def events(request: HttpRequest) -> HttpResponse:
    """Show the event log, filtered, with a live tail."""
    skill_ids, component_ids = services.skill_and_component_ids(actor_of(request))
    return render(
        request,
        "dashboard/events.html",
        {
            "page": "events",
            "robots": services.robot_choices(actor_of(request)),
            "levels": Level.choices,
            "skill_ids": skill_ids,
            "component_ids": component_ids,
            "filters": {key: request.GET.get(key, "") for key in ("robot", "skill", "component", "level")},
        },
    )


@login_required
def rollouts(request: HttpRequest) -> HttpResponse:
    """List the rollouts of the user's organizations, newest first, each robot's status counted."""
    before = request.GET.get("before", "")
    # Past 18 digits an id overflows PostgreSQL's bigint: no rollout has one, so no page starts there.
    older_than = int(before) if before.isdigit() and len(before) <= 18 else None
    rows, older = services.rollout_list(actor_of(request), older_than)
    return render(request, "dashboard/rollouts.html", {"page": "rollouts", "rows": rows, "older": older})


@login_required
def rollout(request: HttpRequest, rollout_id: int) -> HttpResponse:
    """Show one rollout: its batches and robots, live, and the steering buttons of a developer."""
    found = services.rollout_detail(actor_of(request), rollout_id)
    if found is None:
        # Another organization's rollout reads as a missing one.
        raise Http404("No such rollout.")
    data, can_steer = found
    return render(request, "dashboard/rollout.html", {"page": "rollouts", "rollout": data, "can_steer": can_steer})


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

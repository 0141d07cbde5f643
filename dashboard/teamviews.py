"""The dashboard's pages about teams: the organization picker, members and roles, API tokens.

Plain forms posted with the session and its CSRF token; every rule is the same service the
Robot API calls, so the server refuses what a role lacks whatever the page shows.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, TypeVar

from django.contrib.auth.decorators import login_required
from django.core.exceptions import PermissionDenied, ValidationError
from django.http import HttpRequest, HttpResponse
from django.shortcuts import redirect, render
from django.urls import reverse
from django.utils.http import url_has_allowed_host_and_scheme
from django.views.decorators.http import require_POST
from rest_framework.exceptions import PermissionDenied as ApiPermissionDenied

from audit.middleware import describe
from robots import access
from robots.access import actor_of
from teams import services, tokens
from teams.models import Organization
from teams.naming import member_object
from teams.roles import Right, Role

T = TypeVar("T")
NEW_TOKEN = "bridgeos_new_token"


def refused_as_403(call: Callable[[], T]) -> T:
    """Run a service call, turning the API's 403 into Django's so a page answers it as one."""
    try:
        return call()
    except ApiPermissionDenied as exc:
        raise PermissionDenied(str(exc.detail)) from exc


def errors_of(exc: ValidationError) -> list[str]:
    """Return a validation error's messages, each with its field named."""
    if hasattr(exc, "message_dict"):
        return [f"{field}: {message}" for field, messages in exc.message_dict.items() for message in messages]
    return list(exc.messages)


@login_required
@require_POST
def pick_organization(request: HttpRequest) -> HttpResponse:
    """Hold the session's pages to one of the user's organizations, or (empty) to all of them."""
    slug = request.POST.get("organization", "")
    if slug:
        actor = access.Actor(request.user)  # every organization of the user, whatever was picked before
        organization = services.organization_for(actor, slug)
        request.session[access.SESSION_ORGANIZATION] = organization.id
    else:
        request.session.pop(access.SESSION_ORGANIZATION, None)
    following = request.POST.get("next", "")
    safe = url_has_allowed_host_and_scheme(following, {request.get_host()}, require_https=request.is_secure())
    return redirect(following if safe and following else reverse("dashboard:index"))


@login_required
def organizations(request: HttpRequest) -> HttpResponse:
    """List the user's organizations with their role in each, and make a team organization."""
    errors: list[str] = []
    if request.method == "POST":
        try:
            made = services.create_organization(
                request.user, request.POST.get("slug", "").strip(), request.POST.get("name", "").strip()
            )
            return redirect("dashboard:organization", slug=made.slug)
        except ValidationError as exc:
            errors = errors_of(exc)
    rows = services.reachable_organizations(access.Actor(request.user, organization_id=None))
    context = {"page": "team", "organizations": rows, "errors": errors, "form": request.POST}
    return render(request, "dashboard/organizations.html", context, status=400 if errors else 200)


def members_page(request: HttpRequest, organization: Organization, errors: list[str] | None = None) -> HttpResponse:
    """Render an organization's members page, with forms for an admin."""
    actor = actor_of(request)
    context = {
        "page": "team",
        "organization": organization,
        "role": actor.role_in(organization.id),
        "can_administer": actor.may(organization.id, Right.ADMINISTER),
        "members": services.members(organization),
        "roles": Role.choices,
        "tokens": tokens.organization_tokens(organization) if actor.may(organization.id, Right.ADMINISTER) else [],
        "errors": errors or [],
    }
    return render(request, "dashboard/organization.html", context, status=400 if errors else 200)


@login_required
def organization(request: HttpRequest, slug: str) -> HttpResponse:
    """Show an organization's members and roles; an admin adds a member here."""
    actor = actor_of(request)
    if request.method != "POST":
        return members_page(request, refused_as_403(lambda: services.organization_for(actor, slug)))
    username, role = request.POST.get("username", "").strip(), request.POST.get("role", "")
    describe(request, "member.add", member_object(slug, username), role=role[:20])
    found = refused_as_403(lambda: services.organization_for(actor, slug, Right.ADMINISTER))
    try:
        services.add_member(found, username, role)
    except ValidationError as exc:
        return members_page(request, found, errors_of(exc))
    return redirect("dashboard:organization", slug=found.slug)


@login_required
@require_POST
def member(request: HttpRequest, slug: str, username: str) -> HttpResponse:
    """Change a member's role or remove them (an admin; a member may remove themself)."""
    actor = actor_of(request)
    remove = request.POST.get("action") == "remove"
    leaving = remove and username == request.user.get_username()
    action = ("member.leave" if leaving else "member.remove") if remove else "member.role"
    describe(
        request,
        action,
        member_object(slug, username),
        **({} if remove else {"role": request.POST.get("role", "")[:20]}),
    )
    found = refused_as_403(lambda: services.organization_for(actor, slug, Right.READ if leaving else Right.ADMINISTER))
    try:
        if remove:
            services.remove_member(found, username)
        else:
            services.change_role(found, username, request.POST.get("role", ""))
    except ValidationError as exc:
        return members_page(request, found, errors_of(exc))
    if leaving:
        if request.session.get(access.SESSION_ORGANIZATION) == found.id:
            request.session.pop(access.SESSION_ORGANIZATION)
        return redirect("dashboard:organizations")
    return redirect("dashboard:organization", slug=found.slug)


@login_required
def api_tokens(request: HttpRequest) -> HttpResponse:
    """List the user's API tokens and make one; its key is shown on this answer only."""
    actor = access.Actor(request.user)  # a token may be made for any of the user's organizations
    errors: list[str] = []
    made: dict[str, Any] | None = None
    if request.method == "POST":
        days = request.POST.get("expires_in_days", "").strip()
        try:
            if days and not days.isdigit():
                raise ValidationError({"expires_in_days": ["Give a whole number of days, or leave it empty."]})
            services.role_named(request.POST.get("role", ""))
            key, token = tokens.make_token(
                actor,
                name=request.POST.get("name", "").strip()[:100],
                organization_slug=request.POST.get("organization", ""),
                role=request.POST["role"],
                expires_in_days=int(days) if days else None,
            )
            # Redirected, so a reload never posts the form again; the key waits for that one page only.
            request.session[NEW_TOKEN] = {"key": key, "name": token.name}
            return redirect("dashboard:tokens")
        except ValidationError as exc:
            errors = errors_of(exc)
    else:
        made = request.session.pop(NEW_TOKEN, None)
    context = {
        "page": "tokens",
        "tokens": [tokens.token_row(t) for t in tokens.tokens_of(actor)],
        "organizations": services.reachable_organizations(actor),
        "roles": Role.choices,
        "made": made,
        "errors": errors,
        "form": request.POST if errors else {},
    }
    return render(request, "dashboard/tokens.html", context, status=400 if errors else 200)


@login_required
@require_POST
def revoke_api_token(request: HttpRequest, token_id: int) -> HttpResponse:
    """Revoke one of the user's tokens (or, for an admin, one of their organization's) and close its connections."""
    # With every role of the user: a login token is revoked here even while one organization is picked.
    tokens.revoke_token(access.Actor(request.user), token_id)
    following = request.POST.get("next", "")
    safe = url_has_allowed_host_and_scheme(following, {request.get_host()}, require_https=request.is_secure())
    return redirect(following if safe and following else reverse("dashboard:tokens"))

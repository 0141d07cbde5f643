"""The registry credentials a cloud copy's Swarm service carries, so whichever node runs its task can pull.

Swarm keeps the ``X-Registry-Auth`` of a service's create or update request with the service and
hands it to the node that runs each task; that node pulls the pinned ``repo@sha256:…`` with it.
The cloud puts a token there that it mints itself with the registry app's signing key: pull
only, for the one repository of the image, with the rights of the robot's organization (Docker's AuthConfig
``registrytoken``: the node sends it as a bearer token and never calls the realm, which it may
not even reach). It lasts ``BRIDGEOS_REGISTRY_SWARM_TOKEN_S`` from the create or update; every
restart of a copy is an update that carries a fresh one. The Engine API never shows it back
(``docker service inspect`` has no pull options).

The Docker SDK sends only the auth of its client's config file with services, so the two
requests are made here, as the Engine API documents them.
"""

from __future__ import annotations

import base64
import json
from datetime import UTC, datetime
from typing import Any

import docker.errors
import requests
from django.conf import settings
from django.contrib.auth.models import AbstractBaseUser
from docker.api import APIClient

from bridgeos_agent.imagerefs import split_reference
from registry import tokens
from registry.services import principal_of, robot_principal, signing_key
from robots.models import Robot

__all__ = ["PullRefused", "create_service", "encode_auth", "registry_auth", "update_service"]

AUTH_HEADER = "X-Registry-Auth"


class PullRefused(ValueError):
    """The robot's organization may not pull the image the cloud copy would run."""


def encode_auth(token: str, server: str) -> str:
    """Return an X-Registry-Auth value presenting ``token`` to the registry at ``server`` (base64url JSON)."""
    document = json.dumps({"registrytoken": token, "serveraddress": server}).encode()
    return base64.urlsafe_b64encode(document).decode()


def registry_auth(image: str, who: Robot | AbstractBaseUser, *, now: datetime | None = None) -> str:
    """Return the X-Registry-Auth for pulling ``image`` for a robot's organization (or a user); empty when not ours.

    Images of other registries and local images get none from the cloud, as before: a token of
    this cloud means nothing to another registry.
    """
    conf = settings.BRIDGEOS
    host = conf["REGISTRY_HOST"]
    registry, repository, _ = split_reference(image)
    if not host or registry != host:
        return ""
    principal = robot_principal(who) if isinstance(who, Robot) else principal_of(who)
    scope = tokens.Scope("repository", repository, ("pull",))
    if "pull" not in tokens.granted(principal, scope):
        whose = f"robot {who.id}'s organization" if isinstance(who, Robot) else "user"
        raise PullRefused(f"the {whose} {principal.username!r} may not pull {repository!r} (image {image!r})")
    claims = tokens.token_claims(
        principal,
        [scope],
        issuer=conf["REGISTRY_ISSUER"],
        audience=conf["REGISTRY_SERVICE"],
        now=now or datetime.now(UTC),
        ttl_s=conf["REGISTRY_SWARM_TOKEN_S"],
    )
    return encode_auth(tokens.sign(claims, signing_key()), host)


def create_service(api: APIClient, request: dict[str, Any], auth: str) -> dict[str, Any]:
    """Create a service from ``swarmspec.service_config``'s request, carrying ``auth`` for its nodes' pulls."""
    body = {
        "Name": request["name"],
        "Labels": request.get("labels") or {},
        "TaskTemplate": request["task_template"],
        "EndpointSpec": request.get("endpoint_spec"),
    }
    return _post(api, "/services/create", {}, {key: value for key, value in body.items() if value is not None}, auth)


def update_service(api: APIClient, service: dict[str, Any], spec: dict[str, Any], auth: str) -> dict[str, Any]:
    """Replace an inspected service's spec with ``spec``; a new ``auth`` replaces the one Swarm kept."""
    path = f"/services/{service['ID']}/update"
    return _post(api, path, {"version": service["Version"]["Index"]}, spec, auth)


def _post(api: APIClient, path: str, params: dict[str, Any], body: dict[str, Any], auth: str) -> dict[str, Any]:
    """POST a JSON document to the engine, raising the SDK's own APIError when it refuses."""
    headers = {"Content-Type": "application/json"}
    if auth:
        headers[AUTH_HEADER] = auth
    url = f"{api.base_url}/v{api.api_version}{path}"
    response = api.post(url, params=params, data=json.dumps(body), headers=headers, timeout=api.timeout)
    try:
        response.raise_for_status()
    except requests.exceptions.HTTPError as exc:
        docker.errors.create_api_error_from_http_exception(exc)  # raises the SDK's APIError, NotFound...
        raise
    return response.json() if response.content else {}

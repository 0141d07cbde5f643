"""The Skill Router's part of the Skill configuration: its topics, services, actions and HTTP routes."""

from __future__ import annotations

from typing import Annotated

from pydantic import Field, StringConstraints, field_validator, model_validator

from bridgeos_agent.configtypes import (
    HTTP_PREFIX_PATTERN,
    HttpMethod,
    Issue,
    Port,
    RosName,
    RosType,
    Slug,
    StrictModel,
    raise_issues,
    reject_duplicates,
)

__all__ = ["ActionRoute", "HttpRoute", "RouterConfig", "ServiceRoute", "TopicRoute"]


class TopicRoute(StrictModel):
    """Route one ROS topic from its publisher to its subscribers."""

    name: RosName
    type: RosType = Field(description="ROS message type, 'package/Message'.")
    publisher: Slug = Field(description="Id of the component publishing the topic.")
    subscribers: list[Slug] = Field(default_factory=list)
    store: int = Field(
        default=0,
        ge=0,
        le=100_000,
        description="Last N messages kept and replayed to a migrated subscriber.",
    )

    @field_validator("subscribers")
    @classmethod
    def _unique_subscribers(cls, value: list[str]) -> list[str]:
        """Reject a subscriber listed twice."""
        reject_duplicates(value, "subscriber")
        return value


class ServiceRoute(StrictModel):
    """Proxy one ROS service to the component serving it."""

    name: RosName
    type: RosType = Field(description="ROS service type, 'package/Service'.")
    server: Slug = Field(description="Id of the component serving the service.")


class ActionRoute(StrictModel):
    """Relay one ROS 2 action (its goal, result and cancel services and its feedback and status topics)."""

    name: RosName
    type: RosType = Field(description="ROS 2 action type, 'package/action/Action'.")
    server: Slug = Field(description="Id of the component serving the action.")


def _only_get() -> list[HttpMethod]:
    return ["GET"]


class HttpRoute(StrictModel):
    """Proxy HTTP requests under a path prefix to a component."""

    component: Slug
    prefix: Annotated[str, StringConstraints(pattern=HTTP_PREFIX_PATTERN, max_length=256)] = "/"
    methods: list[HttpMethod] = Field(default_factory=_only_get, min_length=1)
    port: Port | None = Field(
        default=None,
        description="Component port to forward to; the first port of its launch spec if unset.",
    )

    @field_validator("methods")
    @classmethod
    def _unique_methods(cls, value: list[str]) -> list[str]:
        """Reject a method listed twice."""
        reject_duplicates(value, "method")
        return value


class RouterConfig(StrictModel):
    """Configure a Skill Router's ROS topics, ROS services and HTTP routes."""

    topics: list[TopicRoute] = Field(default_factory=list)
    services: list[ServiceRoute] = Field(default_factory=list)
    actions: list[ActionRoute] = Field(default_factory=list, description="ROS 2 actions.")
    http: list[HttpRoute] = Field(default_factory=list)

    @model_validator(mode="after")
    def _unique_routes(self) -> RouterConfig:
        """Reject two topics, two services or two HTTP prefixes with the same name."""
        issues: list[Issue] = []
        for field, keys in (
            ("topics", [t.name.lstrip("/") for t in self.topics]),
            ("services", [s.name.lstrip("/") for s in self.services]),
            ("actions", [a.name.lstrip("/") for a in self.actions]),
            ("http", [h.prefix.rstrip("/") or "/" for h in self.http]),
        ):
            seen: set[str] = set()
            for index, key in enumerate(keys):
                if key in seen:
                    what = "prefix" if field == "http" else "name"
                    issues.append(((field, index, what), f"duplicate {what} {key!r}"))
                seen.add(key)
        raise_issues(issues)
        return self

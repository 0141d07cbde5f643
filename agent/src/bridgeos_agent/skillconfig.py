"""Define and validate the Skill configuration file (thesis Table 4.1)."""

from __future__ import annotations

import shlex
from collections.abc import Iterable, Sequence
from importlib import resources
from typing import Annotated, Any, Literal

from pydantic import (
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Field,
    StringConstraints,
    WithJsonSchema,
    field_validator,
    model_validator,
)
from pydantic_core import PydanticCustomError

from bridgeos_agent.policies import cost_function_issues
from bridgeos_agent.rosnames import graph_segment

__all__ = [
    "ComponentConfig",
    "ComponentResources",
    "HttpRoute",
    "LaunchSpec",
    "Location",
    "ManagerConfig",
    "NeuralNetworkConfig",
    "Policy",
    "RouterConfig",
    "ServiceRoute",
    "SkillConfig",
    "TopicRoute",
    "config_issues",
    "load_sample_skill_config",
    "parse_skill_config",
    "skill_config_json_schema",
]

JSON_SCHEMA_DIALECT = "https://json-schema.org/draft/2020-12/schema"

# Ids end up in URLs, container names, ROS namespaces and env values, so keep them plain.
SLUG_PATTERN = r"^[a-z0-9][a-z0-9_-]{0,63}$"
# Docker rejects volume names outside this pattern (moby's RestrictedNamePattern).
VOLUME_PATTERN = r"^[a-zA-Z0-9][a-zA-Z0-9_.-]{1,127}$"
# Absolute or relative ROS graph names; "~" (private) names are refused because the
# router resolves them in its own namespace, not the component's.
ROS_NAME_PATTERN = r"^/?[A-Za-z][A-Za-z0-9_]*(/[A-Za-z][A-Za-z0-9_]*)*$"
# ROS 1 spells a type 'package/Type'; ROS 2 also 'package/msg/Type' (srv, action).
ROS_TYPE_PATTERN = r"^[A-Za-z][A-Za-z0-9_]*/((msg|srv|action)/)?[A-Za-z][A-Za-z0-9_]*$"
IDENTIFIER_PATTERN = r"^[A-Za-z_][A-Za-z0-9_]{0,63}$"
ENV_NAME_PATTERN = r"^[A-Za-z_][A-Za-z0-9_]*$"
HTTP_PREFIX_PATTERN = r"^/[A-Za-z0-9._~!$&'()*+,;=:@%/-]*$"
IMAGE_PATTERN = r"^[^\s]{1,255}$"
# Docker Swarm's constraint syntax: an attribute, == or !=, a value.
PLACEMENT_PATTERN = r"^[A-Za-z][A-Za-z0-9_.-]{0,127} ?(==|!=) ?[^\s]{1,128}$"

Slug = Annotated[str, StringConstraints(pattern=SLUG_PATTERN)]
VolumeName = Annotated[str, StringConstraints(pattern=VOLUME_PATTERN)]
RosName = Annotated[str, StringConstraints(pattern=ROS_NAME_PATTERN, max_length=256)]
RosType = Annotated[str, StringConstraints(pattern=ROS_TYPE_PATTERN, max_length=256)]
Identifier = Annotated[str, StringConstraints(pattern=IDENTIFIER_PATTERN)]
EnvName = Annotated[str, StringConstraints(pattern=ENV_NAME_PATTERN, max_length=256)]
FiniteFloat = Annotated[float, Field(allow_inf_nan=False)]
NonNegative = Annotated[float, Field(ge=0, allow_inf_nan=False)]
Port = Annotated[int, Field(ge=1, le=65535)]
PlacementConstraint = Annotated[str, StringConstraints(pattern=PLACEMENT_PATTERN)]

Location = Literal["robot", "cloud", "either"]
Policy = Literal["energy", "network", "monetary", "performance", "custom"]
Activation = Literal["relu", "tanh", "sigmoid"]
HttpMethod = Literal["GET", "HEAD", "POST", "PUT", "PATCH", "DELETE", "OPTIONS"]

MAX_COST_FUNCTION_LENGTH = 2000

Issue = tuple[tuple[str | int, ...], str]


def _split_command(value: Any) -> Any:
    """Split a command given as one string the way a shell would, without a shell."""
    if isinstance(value, str):
        try:
            return shlex.split(value)
        except ValueError as exc:
            raise ValueError(f"cannot split command string: {exc}") from None
    return value


Command = Annotated[
    list[str],
    BeforeValidator(_split_command),
    WithJsonSchema(
        {
            "anyOf": [
                {"type": "array", "items": {"type": "string"}},
                {"type": "string"},
            ],
            "description": "Argument vector, or one string split like a shell would.",
        },
        mode="validation",
    ),
]


def _unique(values: Sequence[Any], what: str) -> None:
    """Reject a sequence that holds the same value twice."""
    seen: set[Any] = set()
    for value in values:
        if value in seen:
            raise ValueError(f"duplicate {what} {value!r}")
        seen.add(value)


def _raise_issues(issues: list[Issue]) -> None:
    """Raise one error carrying every cross-field issue with its own relative path."""
    if issues:
        summary = "; ".join(f"{'.'.join(str(p) for p in path)}: {msg}" if path else msg for path, msg in issues)
        raise PydanticCustomError(
            "skill_config",
            "{summary}",
            {"summary": summary, "issues": tuple(issues)},
        )


def config_issues(ctx: dict[str, Any] | None) -> list[Issue]:
    """Return the per-path issues a cross-field validator attached to an error's ctx."""
    if not ctx:
        return []
    issues = ctx.get("issues") or ()
    return [(tuple(path), str(msg)) for path, msg in issues]


class _Model(BaseModel):
    """Reject unknown fields so typos surface as errors instead of silent defaults."""

    model_config = ConfigDict(extra="forbid", str_strip_whitespace=False)


class NeuralNetworkConfig(_Model):
    """Shape and train the per-component decision network (Algorithms 8 and 9)."""

    hidden_layers: list[Annotated[int, Field(ge=1, le=1024)]] = Field(
        default_factory=lambda: [16, 16],
        max_length=8,
        description="Nodes in each hidden layer, input to output.",
    )
    activation: Activation = "relu"
    learning_rate: float = Field(default=0.01, gt=0, le=1, allow_inf_nan=False)
    trained_after: int = Field(
        default=1000,
        ge=1,
        le=1_000_000,
        description="Samples (decisions) before the network's predictions are trusted.",
    )
    train_every: int = Field(
        default=10,
        ge=1,
        le=100_000,
        description="Decisions between two retraining steps of a trained network.",
    )
    warmup_train_every: int = Field(
        default=4,
        ge=1,
        le=100_000,
        description="Decisions between two training steps while the network warms up (every one is recorded).",
    )
    train_steps: int = Field(
        default=1,
        ge=1,
        le=100,
        description="Training steps each time training is due: more learn from fewer outcomes, at that cost.",
    )


class ManagerConfig(_Model):
    """Configure a Skill Manager's dynamic offloading decisions."""

    policy: Policy = Field(
        default="performance",
        description="Offloading policy whose cost functions (eq. 4.1-4.6) drive decisions.",
    )
    threshold: FiniteFloat = Field(
        default=0.1,
        description="Minimum predicted migration reward before a component migrates.",
    )
    decision_interval: float = Field(
        default=5.0,
        gt=0,
        le=3600,
        allow_inf_nan=False,
        description="Seconds between two offloading decisions for a component.",
    )
    hysteresis: NonNegative = Field(
        default=0.05,
        description="Margin the migration reward must clear above the threshold, so noise does not flap.",
    )
    cooldown: float = Field(
        default=30.0,
        ge=0,
        le=86_400,
        allow_inf_nan=False,
        description="Seconds a component stays put after a move before it may move again.",
    )
    noise_margin: float = Field(
        default=4.0,
        ge=0,
        le=100,
        allow_inf_nan=False,
        description=(
            "A reward above threshold + hysteresis but within this many standard deviations of its recent"
            " noise moves only if the two decisions before cleared it too (0: never waits)."
        ),
    )
    neural_network: NeuralNetworkConfig = Field(default_factory=NeuralNetworkConfig)
    constants: dict[Identifier, FiniteFloat] = Field(
        default_factory=dict,
        description="Named constants the cost functions may read (e.g. weights, prices).",
    )
    cost_functions: dict[
        Identifier, Annotated[str, StringConstraints(min_length=1, max_length=MAX_COST_FUNCTION_LENGTH)]
    ] = Field(
        default_factory=dict,
        description="Custom policy cost expressions keyed by location ('robot', 'cloud').",
    )

    @model_validator(mode="after")
    def _cost_functions_are_usable(self) -> ManagerConfig:
        """Require safe, well-keyed cost functions, and one per location when the policy is custom."""
        issues: list[Issue] = []
        if self.policy == "custom":
            missing = [loc for loc in ("robot", "cloud") if loc not in self.cost_functions]
            issues += [(("cost_functions",), f"policy 'custom' needs a cost function for {loc!r}") for loc in missing]
        for key, message in cost_function_issues(self.cost_functions, self.constants):
            issues.append((("cost_functions",) if key is None else ("cost_functions", key), message))
        _raise_issues(issues)
        return self


class TopicRoute(_Model):
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
        _unique(value, "subscriber")
        return value


class ServiceRoute(_Model):
    """Proxy one ROS service to the component serving it."""

    name: RosName
    type: RosType = Field(description="ROS service type, 'package/Service'.")
    server: Slug = Field(description="Id of the component serving the service.")


class ActionRoute(_Model):
    """Relay one ROS 2 action (its goal, result and cancel services and its feedback and status topics)."""

    name: RosName
    type: RosType = Field(description="ROS 2 action type, 'package/action/Action'.")
    server: Slug = Field(description="Id of the component serving the action.")


def _only_get() -> list[HttpMethod]:
    return ["GET"]


class HttpRoute(_Model):
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
        _unique(value, "method")
        return value


class RouterConfig(_Model):
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
        _raise_issues(issues)
        return self


class ComponentResources(_Model):
    """State what a component needs to run: the allocator's requiredResources."""

    cpu: NonNegative = Field(default=0.0, description="CPU cores.")
    gpu: int = Field(default=0, ge=0, le=64, description="GPUs.")
    ram: NonNegative = Field(default=0.0, description="Memory in MiB.")
    bandwidth: NonNegative = Field(default=0.0, description="Network in Mbit/s.")
    io: NonNegative = Field(default=0.0, description="Disk I/O in MB/s.")


class LaunchSpec(_Model):
    """Say how to start a component in one location, with Docker or as a process."""

    image: Annotated[str, StringConstraints(pattern=IMAGE_PATTERN)] | None = Field(
        default=None, description="Docker image (docker and swarm runtimes)."
    )
    command: Command | None = Field(
        default=None,
        description="Command to run (the process runtime; overrides the image's CMD).",
    )
    env: dict[EnvName, str] = Field(default_factory=dict)
    ports: list[Port] = Field(default_factory=list, max_length=64)
    placement: list[PlacementConstraint] = Field(
        default_factory=list,
        max_length=32,
        description="Swarm placement constraints for the cloud copy, e.g. 'node.labels.gpu==true'.",
    )

    @field_validator("ports")
    @classmethod
    def _unique_ports(cls, value: list[int]) -> list[int]:
        """Reject a port listed twice."""
        _unique(value, "port")
        return value

    @field_validator("command")
    @classmethod
    def _nonempty_command(cls, value: list[str] | None) -> list[str] | None:
        """Reject an empty command, which would start nothing."""
        if value is not None and not value:
            raise ValueError("command must not be empty")
        return value

    @model_validator(mode="after")
    def _image_or_command(self) -> LaunchSpec:
        """Require something to start: an image, a command, or both."""
        if self.image is None and self.command is None:
            _raise_issues([((), "a launch spec needs an 'image' or a 'command'")])
        return self


class ComponentConfig(_Model):
    """Describe one Skill component and how to launch it on the robot and in the cloud."""

    name: Annotated[str, StringConstraints(min_length=1, max_length=128)]
    location: Location = Field(description="Where the component may run: 'robot', 'cloud' or 'either' (movable).")
    links: list[Slug] = Field(
        default_factory=list,
        description="Ids of components that must always run in the same location as this one.",
    )
    resources: ComponentResources = Field(default_factory=ComponentResources)
    ros: bool | Literal[2] = Field(
        default=True,
        description="The ROS the component speaks: true (or 1) for ROS 1, 2 for ROS 2, false when it is no ROS node.",
    )
    robot: LaunchSpec | None = Field(default=None, description="Launch spec on the robot.")
    cloud: LaunchSpec | None = Field(default=None, description="Launch spec in the cloud.")

    @field_validator("links")
    @classmethod
    def _unique_links(cls, value: list[str]) -> list[str]:
        """Reject a link listed twice."""
        _unique(value, "link")
        return value

    @model_validator(mode="after")
    def _launch_specs_for_location(self) -> ComponentConfig:
        """Require a launch spec for every location the component may run in."""
        needed = ("robot", "cloud") if self.location == "either" else (self.location,)
        _raise_issues(
            [
                ((loc,), f"location {self.location!r} requires a {loc!r} launch spec")
                for loc in needed
                if getattr(self, loc) is None
            ]
        )
        return self

    @property
    def ros_version(self) -> Literal[0, 1, 2]:
        """Return 1 or 2 for the ROS the component speaks, 0 when it is no ROS node."""
        if self.ros is False:
            return 0
        return 1 if self.ros is True else 2

    def launch_spec(self, location: Literal["robot", "cloud"]) -> LaunchSpec | None:
        """Return the launch spec for one concrete location."""
        return self.robot if location == "robot" else self.cloud


class SkillConfig(_Model):
    """Validate a whole Skill configuration file (thesis Table 4.1)."""

    model_config = ConfigDict(
        extra="forbid",
        title="bridgeOS Skill configuration",
        json_schema_extra={"$schema": JSON_SCHEMA_DIALECT},
    )

    skill: Annotated[str, StringConstraints(min_length=1, max_length=128)] = Field(description="Skill name.")
    skill_id: Slug = Field(description="Skill unique identifier.")
    volumes: list[VolumeName] = Field(default_factory=list, description="Docker volumes the Skill requires.")
    compose: dict[str, Any] = Field(
        default_factory=dict,
        description="Docker Compose fragment deploying the Skill's manager and router.",
    )
    manager: ManagerConfig = Field(default_factory=ManagerConfig)
    router: RouterConfig = Field(default_factory=RouterConfig)
    components: dict[Slug, ComponentConfig] = Field(
        min_length=1, description="Components of the Skill, keyed by component id."
    )

    @field_validator("volumes")
    @classmethod
    def _unique_volumes(cls, value: list[str]) -> list[str]:
        """Reject a volume listed twice."""
        _unique(value, "volume")
        return value

    @model_validator(mode="after")
    def _cross_references(self) -> SkillConfig:
        """Check links and routes name real components in compatible locations."""
        issues: list[Issue] = []
        issues += self._name_issues()
        issues += self._link_issues()
        issues += self._route_issues()
        _raise_issues(issues)
        return self

    def _name_issues(self) -> Iterable[Issue]:
        """Report two components with the same display name or the same ROS namespace."""
        segments: dict[str, str] = {}
        for cid in self.components:
            other = segments.setdefault(graph_segment(cid), cid)
            if other != cid:
                yield (
                    ("components", cid),
                    f"component ids {other!r} and {cid!r} would share a ROS namespace ('-' reads as '_')",
                )
        seen: dict[str, str] = {}
        for cid, component in self.components.items():
            key = component.name.strip().casefold()
            if key in seen:
                yield (
                    ("components", cid, "name"),
                    f"name {component.name!r} is already used by component {seen[key]!r}",
                )
            else:
                seen[key] = cid

    def _link_issues(self) -> Iterable[Issue]:
        """Report dangling links, self-links and link groups pinned to both locations."""
        parent = {cid: cid for cid in self.components}

        def find(cid: str) -> str:
            while parent[cid] != cid:
                parent[cid] = parent[parent[cid]]
                cid = parent[cid]
            return cid

        dangling = False
        for cid, component in self.components.items():
            for index, other in enumerate(component.links):
                path = ("components", cid, "links", index)
                if other == cid:
                    yield path, f"component {cid!r} cannot link to itself"
                elif other not in self.components:
                    dangling = True
                    yield path, f"unknown component {other!r}"
                else:
                    there = self.components[other].location
                    if {component.location, there} == {"robot", "cloud"}:
                        yield (
                            path,
                            f"linked components must share a location, but {cid!r} is "
                            f"{component.location!r} and {other!r} is {there!r}",
                        )
                    parent[find(cid)] = find(other)
        if dangling:
            return
        # Links are transitive: a robot-only and a cloud-only component joined through
        # 'either' components can never be co-located either.
        groups: dict[str, list[str]] = {}
        for cid in self.components:
            groups.setdefault(find(cid), []).append(cid)
        for members in groups.values():
            pinned = {self.components[m].location for m in members} - {"either"}
            direct = any(
                {self.components[m].location, self.components[o].location} == {"robot", "cloud"}
                for m in members
                for o in self.components[m].links
                if o in self.components
            )
            if len(pinned) > 1 and not direct:
                first = members[0]
                yield (
                    ("components", first, "links"),
                    "linked group "
                    + ", ".join(repr(m) for m in sorted(members))
                    + " mixes 'robot' and 'cloud' components, so it can never share a location",
                )

    def _route_issues(self) -> Iterable[Issue]:
        """Report routes naming unknown components, non-ROS components or components of another ROS."""

        def check(path: tuple[str | int, ...], cid: str, ros: int | None) -> Iterable[Issue]:
            component = self.components.get(cid)
            if component is None:
                yield path, f"unknown component {cid!r}"
            elif ros is not None and not component.ros_version:
                yield path, f"component {cid!r} is not a ROS node (ros: false)"
            elif ros and component.ros_version != ros:
                # The router relays bytes; it does not translate between ROS 1 and ROS 2 messages.
                yield path, f"component {cid!r} speaks ROS {component.ros_version}, the route's publisher ROS {ros}"

        def version(cid: str) -> int:
            component = self.components.get(cid)
            return component.ros_version if component is not None else 0

        for index, topic in enumerate(self.router.topics):
            base = ("router", "topics", index)
            yield from check((*base, "publisher"), topic.publisher, 0)
            for sub_index, sub in enumerate(topic.subscribers):
                yield from check((*base, "subscribers", sub_index), sub, version(topic.publisher))
            if version(topic.publisher) == 1 and topic.type.count("/") > 1:
                yield (*base, "type"), f"ROS 1 types are spelled 'package/Type', not {topic.type!r}"
        for index, service in enumerate(self.router.services):
            yield from check(("router", "services", index, "server"), service.server, 0)
        for index, action in enumerate(self.router.actions):
            yield from check(("router", "actions", index, "server"), action.server, 0)
            if version(action.server) == 1:
                yield ("router", "actions", index, "server"), "actions are routed for ROS 2 components only"
        for index, route in enumerate(self.router.http):
            yield from check(("router", "http", index, "component"), route.component, None)

    def linked_components(self, component_id: str) -> list[str]:
        """Return every component transitively linked to one, excluding itself."""
        neighbours: dict[str, set[str]] = {cid: set() for cid in self.components}
        for cid, component in self.components.items():
            for other in component.links:
                neighbours[cid].add(other)
                neighbours[other].add(cid)
        seen = {component_id}
        stack = [component_id]
        while stack:
            for other in neighbours[stack.pop()]:
                if other not in seen:
                    seen.add(other)
                    stack.append(other)
        seen.discard(component_id)
        return sorted(seen)


def skill_config_json_schema() -> dict[str, Any]:
    """Return the JSON Schema of a Skill configuration file."""
    return SkillConfig.model_json_schema(mode="validation")


def parse_skill_config(data: dict[str, Any] | str | bytes) -> SkillConfig:
    """Parse and validate a Skill configuration from a dict or JSON text."""
    if isinstance(data, str | bytes | bytearray):
        return SkillConfig.model_validate_json(data)
    return SkillConfig.model_validate(data)


def load_sample_skill_config(name: str = "people_detection") -> SkillConfig:
    """Load one of the sample Skill configurations shipped with the package."""
    if not name.replace("_", "").isalnum():
        raise ValueError(f"invalid sample name {name!r}")
    text = resources.files("bridgeos_agent").joinpath("samples").joinpath(f"{name}.json").read_text()
    return parse_skill_config(text)

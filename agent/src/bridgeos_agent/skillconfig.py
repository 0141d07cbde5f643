"""Define and validate the Skill configuration file (thesis Table 4.1)."""

from __future__ import annotations

from collections.abc import Iterable
from importlib import resources
from typing import Annotated, Any, Literal

from pydantic import (
    ConfigDict,
    Field,
    StringConstraints,
    field_validator,
    model_validator,
)

from bridgeos_agent.configtypes import (
    ENV_NAME_PATTERN,
    HTTP_PREFIX_PATTERN,
    IDENTIFIER_PATTERN,
    IMAGE_PATTERN,
    JSON_SCHEMA_DIALECT,
    MAX_COST_FUNCTION_LENGTH,
    PLACEMENT_PATTERN,
    ROS_NAME_PATTERN,
    ROS_TYPE_PATTERN,
    SLUG_PATTERN,
    VOLUME_PATTERN,
    Activation,
    Command,
    EnvName,
    FiniteFloat,
    Identifier,
    Issue,
    Location,
    NonNegative,
    PlacementConstraint,
    Policy,
    Port,
    Slug,
    StrictModel,
    VolumeName,
    config_issues,
    raise_issues,
    reject_duplicates,
)
from bridgeos_agent.policies import cost_function_issues
from bridgeos_agent.rosnames import graph_segment
from bridgeos_agent.routeconfig import ActionRoute, HttpRoute, RouterConfig, ServiceRoute, TopicRoute

__all__ = [
    "ENV_NAME_PATTERN",
    "HTTP_PREFIX_PATTERN",
    "IDENTIFIER_PATTERN",
    "IMAGE_PATTERN",
    "PLACEMENT_PATTERN",
    "ROS_NAME_PATTERN",
    "ROS_TYPE_PATTERN",
    "SLUG_PATTERN",
    "VOLUME_PATTERN",
    "ActionRoute",
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
    "UpdateConfig",
    "config_issues",
    "load_sample_skill_config",
    "parse_skill_config",
    "skill_config_json_schema",
]


class NeuralNetworkConfig(StrictModel):
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


class ManagerConfig(StrictModel):
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
        raise_issues(issues)
        return self


class ComponentResources(StrictModel):
    """State what a component needs to run: the allocator's requiredResources."""

    cpu: NonNegative = Field(default=0.0, description="CPU cores.")
    gpu: int = Field(default=0, ge=0, le=64, description="GPUs.")
    ram: NonNegative = Field(default=0.0, description="Memory in MiB.")
    bandwidth: NonNegative = Field(default=0.0, description="Network in Mbit/s.")
    io: NonNegative = Field(default=0.0, description="Disk I/O in MB/s.")


class LaunchSpec(StrictModel):
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
        reject_duplicates(value, "port")
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
            raise_issues([((), "a launch spec needs an 'image' or a 'command'")])
        return self


class ComponentConfig(StrictModel):
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
        reject_duplicates(value, "link")
        return value

    @model_validator(mode="after")
    def _launch_specs_for_location(self) -> ComponentConfig:
        """Require a launch spec for every location the component may run in."""
        needed = ("robot", "cloud") if self.location == "either" else (self.location,)
        raise_issues(
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


class UpdateConfig(StrictModel):
    """Say how a new version of the Skill takes over from the running one on a robot (balena's update strategies)."""

    strategy: Literal["replace", "beside"] = Field(
        default="replace",
        description=(
            "replace: the running version stops, then the new one starts. beside: the new version's robot "
            "components start beside the running ones, which stop once the new ones run (a hand-over), where "
            "the robot has the memory for both; else it replaces."
        ),
    )
    settle_s: float = Field(
        default=2.0,
        ge=0,
        le=300,
        description=(
            "beside: how long every new component must run, with no crash or restart, before the old "
            "copies stop; a new version that does not puts the old copies back."
        ),
    )


class SkillConfig(StrictModel):
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
    update: UpdateConfig = Field(default_factory=UpdateConfig)
    components: dict[Slug, ComponentConfig] = Field(
        min_length=1, description="Components of the Skill, keyed by component id."
    )

    @field_validator("volumes")
    @classmethod
    def _unique_volumes(cls, value: list[str]) -> list[str]:
        """Reject a volume listed twice."""
        reject_duplicates(value, "volume")
        return value

    @model_validator(mode="after")
    def _cross_references(self) -> SkillConfig:
        """Check links and routes name real components in compatible locations."""
        issues: list[Issue] = []
        issues += self._name_issues()
        issues += self._link_issues()
        issues += self._route_issues()
        raise_issues(issues)
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

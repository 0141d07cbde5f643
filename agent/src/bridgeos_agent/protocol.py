"""Define every robot⇄cloud⇄client WebSocket message once: envelope, events, payloads, codec.

Sans-IO: nothing here touches a socket, an event loop or a clock. Times come in as
``now`` arguments (seconds, any monotonic or wall origin the caller picks), so the
cloud's Channels consumers and the agent's transport share this module and its tests.

Longer than 600 lines on purpose: this file is the one definition of every message (thesis
Table 3.3) and of the reliability core both sides run; splitting it would scatter the
definition the cloud and the robot must agree on.
"""

from __future__ import annotations

import enum
import heapq
import itertools
import os
import random as _random
import re
import struct
from collections import OrderedDict
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from typing import Annotated, Any, Literal, NotRequired

from pydantic import (
    AfterValidator,
    BaseModel,
    ConfigDict,
    Field,
    IPvAnyAddress,
    Strict,
    StringConstraints,
    ValidationError,
    model_validator,
    with_config,
)
from typing_extensions import TypedDict  # pydantic needs this one before Python 3.12

from bridgeos_agent.skillconfig import SLUG_PATTERN

__all__ = [
    "BRIDGE_BINARY_CHARS",
    "BRIDGE_BLOB_MAX_BYTES",
    "BRIDGE_BLOB_MIN_BYTES",
    "BRIDGE_HEAD_BYTES",
    "BRIDGE_KINDS",
    "BRIDGE_PART_CHARS",
    "COMMANDS",
    "CRASH_LOG_LINES",
    "DIRECTIONS",
    "EVENTS",
    "LOG_LEVELS",
    "MAX_FRAME_BYTES",
    "MAX_LOG_LINES_PER_FRAME",
    "MAX_LOG_LINE_CHARS",
    "MAX_LOG_TAIL",
    "MAX_METRICS_PER_FRAME",
    "PAYLOADS",
    "RECORDING_CHUNK_BYTES",
    "REPLIES",
    "REQUIRES_ACK",
    "Ack",
    "AuthenticationClient",
    "AuthenticationFailure",
    "AuthenticationRobot",
    "AuthenticationSuccess",
    "BlobWindow",
    "BridgeClose",
    "BridgeFrame",
    "BridgeOpen",
    "ComponentInformation",
    "ComponentLocation",
    "ComponentLogs",
    "ComponentLogsGet",
    "ComponentMigrate",
    "ComponentStart",
    "ComponentStatus",
    "ComponentStatusGet",
    "ComponentStatusName",
    "ComponentStop",
    "ComponentsApi",
    "ComponentsApiReply",
    "ConnectionEstablished",
    "ConnectionLost",
    "ContainerInfo",
    "Correlator",
    "Dedup",
    "Direction",
    "Envelope",
    "ErrorMessage",
    "Event",
    "IdGenerator",
    "Location",
    "LogLine",
    "LogsSubscribe",
    "LogsUnsubscribe",
    "MetricPoint",
    "MetricsGet",
    "MetricsPayload",
    "MetricsSubscribe",
    "Offloading",
    "OffloadingDecision",
    "OffloadingGet",
    "OffloadingMode",
    "Payload",
    "Pending",
    "ProtocolError",
    "PullProgress",
    "RecordingChunk",
    "RecordingStart",
    "RecordingStatus",
    "RecordingStatusName",
    "RecordingStop",
    "Reliable",
    "RobotConfigGet",
    "RobotConfigPayload",
    "RobotConfigUpdate",
    "RobotRekey",
    "RobotStart",
    "RobotStop",
    "Ros2GraphInfo",
    "Shutdown",
    "SkillConfigGet",
    "SkillConfigPayload",
    "SkillConnect",
    "SkillStart",
    "SkillStatus",
    "SkillStatusGet",
    "SkillStatusName",
    "SkillStop",
    "UpdateHold",
    "VolumeChanges",
    "VolumeChunk",
    "VolumeChunkRef",
    "VolumeChunks",
    "VolumeChunksGet",
    "VolumeFile",
    "ack_frame",
    "decode",
    "decode_bridge_blob",
    "encode",
    "encode_bridge_blob",
    "error_frame",
    "is_allowed",
    "is_bridge_blob",
    "make",
    "new_id",
    "parse_payload",
]

MAX_FRAME_BYTES = 1_048_576
MAX_METRICS_PER_FRAME = 10_000
# The robots one metrics_subscribe may name: the fleet page shows 100 at a time.
MAX_SUBSCRIBED_ROBOTS = 1000
# The lines of its log a crashed component's status report and event carry.
CRASH_LOG_LINES = 50
# The longest a robot's updates may be held (a rollout installs past the deadline anyway).
MAX_HOLD_S = 7 * 24 * 3600.0


# --------------------------------------------------------------------------- events


class Event(enum.StrEnum):
    """Name every WebSocket event (thesis Table 3.3, plus ``ack``)."""

    AUTHENTICATION_CLIENT = "authentication_client"
    AUTHENTICATION_ROBOT = "authentication_robot"
    AUTHENTICATION_SUCCESS = "authentication_success"
    AUTHENTICATION_FAILURE = "authentication_failure"
    CONNECTION_ESTABLISHED = "connection_established"
    CONNECTION_LOST = "connection_lost"
    ERROR_MESSAGE = "error_message"
    SHUTDOWN = "shutdown"
    ROBOT_START = "robot_start"
    ROBOT_STOP = "robot_stop"
    ROBOT_CONFIG = "robot_config"
    ROBOT_CONFIG_GET = "robot_config_get"
    ROBOT_CONFIG_UPDATE = "robot_config_update"
    OFFLOADING = "offloading"
    OFFLOADING_GET = "offloading_get"
    SKILL_START = "skill_start"
    SKILL_STOP = "skill_stop"
    SKILL_STATUS = "skill_status"
    SKILL_STATUS_GET = "skill_status_get"
    # The thesis's table spells it "skill_connnect"; that is a typo and is rejected.
    SKILL_CONNECT = "skill_connect"
    SKILL_CONFIG = "skill_config"
    SKILL_CONFIG_GET = "skill_config_get"
    COMPONENT_START = "component_start"
    COMPONENT_STOP = "component_stop"
    COMPONENT_INFORMATION = "component_information"
    COMPONENT_STATUS = "component_status"
    COMPONENT_STATUS_GET = "component_status_get"
    COMPONENT_LOCATION = "component_location"
    COMPONENT_MIGRATE = "component_migrate"
    METRICS = "metrics"
    METRICS_GET = "metrics_get"
    # Skill volumes kept in step between the robot and the cloud (thesis §3.3.2), not in Table 3.3.
    VOLUME_CHANGES = "volume_changes"
    VOLUME_CHUNKS_GET = "volume_chunks_get"
    VOLUME_CHUNKS = "volume_chunks"
    ACK = "ack"
    # Not in the thesis: the Skill Manager's log of each move it decided (issue 6).
    OFFLOADING_DECISION = "offloading_decision"
    # Not in the thesis: a cloud copy's Components API call, relayed to its Skill's manager.
    COMPONENTS_API = "components_api"
    COMPONENTS_API_REPLY = "components_api_reply"
    # Not in the thesis: an entry of the cloud's event log, pushed to dashboards as it is written (issue 21).
    LOG_EVENT = "log_event"
    # bridges: a rosbridge or Foxglove WebSocket client of the cloud, relayed over the robot's link (issue 19).
    BRIDGE_OPEN = "bridge_open"
    BRIDGE_FRAME = "bridge_frame"
    BRIDGE_CLOSE = "bridge_close"
    # recordings: MCAP recordings of a robot's topics, kept by the cloud (issue 19).
    RECORDING_START = "recording_start"
    RECORDING_STOP = "recording_stop"
    RECORDING_CHUNK = "recording_chunk"
    RECORDING_STATUS = "recording_status"
    # Not in the thesis: a connected robot's new token, given when its token is rotated with a grace.
    ROBOT_REKEY = "robot_rekey"
    # rollouts: a component holds its robot's updates while it is busy (the Components API's /hold).
    UPDATE_HOLD = "update_hold"
    # component logs: what components print, shipped by robots, kept by the cloud, tailed by clients (issue 36).
    COMPONENT_LOGS = "component_logs"
    COMPONENT_LOGS_GET = "component_logs_get"
    LOGS_SUBSCRIBE = "logs_subscribe"
    LOGS_UNSUBSCRIBE = "logs_unsubscribe"
    # Not in the thesis: a client's choice of the robots whose live metrics it is sent (issue 37).
    METRICS_SUBSCRIBE = "metrics_subscribe"


EVENTS: frozenset[str] = frozenset(e.value for e in Event)


class Direction(enum.StrEnum):
    """Name the four legs a frame can travel."""

    ROBOT_TO_CLOUD = "robot_to_cloud"
    CLOUD_TO_ROBOT = "cloud_to_robot"
    CLIENT_TO_CLOUD = "client_to_cloud"
    CLOUD_TO_CLIENT = "cloud_to_client"


class Location(enum.StrEnum):
    """Name where a component runs; ``either`` is only meaningful in configs."""

    ROBOT = "robot"
    CLOUD = "cloud"
    EITHER = "either"


class OffloadingMode(enum.StrEnum):
    """Name how a robot decides component locations."""

    AUTO = "auto"
    MANUAL = "manual"
    ROBOT = "robot"
    CLOUD = "cloud"


class SkillStatusName(enum.StrEnum):
    """Name the lifecycle states of a Skill."""

    STOPPED = "stopped"
    STARTING = "starting"
    RUNNING = "running"
    STOPPING = "stopping"
    FAILED = "failed"


class ComponentStatusName(enum.StrEnum):
    """Name the lifecycle states of a component."""

    PENDING = "pending"
    STARTING = "starting"
    RUNNING = "running"
    MIGRATING = "migrating"
    STOPPING = "stopping"
    STOPPED = "stopped"
    FAILED = "failed"


# --------------------------------------------------------------------------- field types

_ID_PATTERN = r"^[A-Za-z0-9_\-:.]{1,64}$"
_ID_RE = re.compile(_ID_PATTERN)


def is_valid_id(value: object) -> bool:
    """Tell whether a value can serve as a frame id (or a reply_to)."""
    return isinstance(value, str) and _ID_RE.fullmatch(value) is not None


MessageId = Annotated[str, StringConstraints(pattern=_ID_PATTERN)]
Slug = Annotated[str, StringConstraints(pattern=SLUG_PATTERN)]
# Printable ASCII without spaces: covers DRF hex keys and token_urlsafe alike.
Token = Annotated[str, StringConstraints(pattern=r"^[!-~]{1,256}$")]
UserName = Annotated[str, StringConstraints(min_length=1, max_length=150)]
SessionId = Annotated[str, StringConstraints(min_length=1, max_length=128)]
Reason = Annotated[str, StringConstraints(min_length=1, max_length=1000)]
Message = Annotated[str, StringConstraints(min_length=1, max_length=2000)]
FieldPath = Annotated[str, StringConstraints(min_length=1, max_length=256)]
ErrorCode = Annotated[str, StringConstraints(pattern=r"^[a-z][a-z0-9_]{0,63}$")]
Url = Annotated[str, StringConstraints(pattern=r"^https?://[!-~]{1,2040}$")]
MetricName = Annotated[str, StringConstraints(pattern=r"^[A-Za-z_][A-Za-z0-9_.:-]{0,127}$")]
LabelKey = Annotated[str, StringConstraints(pattern=r"^[A-Za-z_][A-Za-z0-9_.-]{0,63}$")]
LabelValue = Annotated[str, StringConstraints(max_length=256)]
ShortText = Annotated[str, StringConstraints(min_length=1, max_length=256)]
RobotLabels = Annotated[
    dict[Annotated[str, StringConstraints(max_length=256)], Annotated[str, StringConstraints(max_length=256)]],
    Field(max_length=256),
]
# Strict so "1.5" or true never sneak in as numbers.
FiniteFloat = Annotated[float, Strict(), Field(allow_inf_nan=False)]
Timestamp = Annotated[float, Strict(), Field(ge=0, allow_inf_nan=False)]
Port = Annotated[int, Strict(), Field(ge=1, le=65535)]
PortText = Annotated[str, StringConstraints(pattern=r"^[1-9][0-9]{0,4}$")]
PortList = Annotated[list[Port], Field(max_length=64)]
PortMap = Annotated[dict[PortText, Port], Field(max_length=64)]
JsonObject = Annotated[dict[str, Any], Field(max_length=1024)]


def _robot_or_cloud(location: Location) -> Location:
    if location is Location.EITHER:
        raise ValueError("'either' is only allowed in configs; use 'robot' or 'cloud'")
    return location


Target = Annotated[Location, AfterValidator(_robot_or_cloud)]


# --------------------------------------------------------------------------- payloads


class Payload(BaseModel):
    """Base of every event payload: closed, immutable."""

    model_config = ConfigDict(extra="forbid", frozen=True)


class RobotScoped(Payload):
    """Base of payloads about one robot.

    ``robot`` names the robot on client links (a client socket is not bound to one);
    on a robot's own link it may be omitted, and the cloud trusts the socket instead.
    """

    robot: Slug | None = None


class AuthenticationClient(Payload):
    """Authenticate a dashboard or app; no token means the session cookie is used."""

    token: Token | None = None


HostPort = Annotated[str, StringConstraints(pattern=r"^[A-Za-z0-9.:\[\]-]{1,253}:[1-9][0-9]{0,4}$")]


class Ros2GraphInfo(Payload):
    """A robot's ROS 2 graph as its agent runs it (``bridgeos_agent.ros2graph.Ros2Graph``)."""

    domain_id: int = Field(default=0, ge=0, le=232)
    rmw: Annotated[str, StringConstraints(pattern=r"^rmw_[a-z0-9_]{1,60}$")] = "rmw_fastrtps_cpp"
    discovery_range: Literal["OFF", "LOCALHOST", "SUBNET", "SYSTEM_DEFAULT"] = "LOCALHOST"
    static_peers: list[Annotated[str, StringConstraints(pattern=r"^[A-Za-z0-9.:-]{1,253}$")]] = Field(
        default_factory=list, max_length=64
    )
    discovery_server: HostPort | None = None


class AuthenticationRobot(Payload):
    """Authenticate a robot with its id and token, saying which ROS master it found (None: none)."""

    robot: Slug
    token: Token
    ros_master: Url | None = None
    # The robot's ROS 2 graph, when its agent can run ROS 2 (None: no rclpy there).
    ros2: Ros2GraphInfo | None = None
    # Labels the robot asks for at its first registration (`bridgeos-agent run --label`): the cloud applies
    # them only while the robot has none, and refuses the login when they break the rules of
    # `bridgeos_agent.labels` (only sizes are bounded here, so the refusal can name the bad key).
    labels: RobotLabels | None = None


class CloudRelayInfo(Payload):
    """Where a robot's router reaches the cloud relay of one of its Skills, and the relay's token."""

    url: Url
    token: Token


class AuthenticationSuccess(Payload):
    """Confirm authentication of a robot or a user."""

    robot: Slug | None = None
    user: UserName | None = None
    session: SessionId | None = None
    # For a robot: the ROS master its components should use (its own, or one the cloud runs).
    ros_master: Url | None = None
    # For a ROS 2 robot: "host:port" of the discovery server the cloud runs for its cloud graph.
    ros2_discovery_server: HostPort | None = None
    # For a robot: the cloud relay the cloud runs per Skill (cloud-side routing), by Skill id.
    cloud_relays: dict[Slug, CloudRelayInfo] | None = Field(default=None, max_length=1000)


class AuthenticationFailure(Payload):
    """Refuse authentication, saying why."""

    reason: Reason


class ConnectionEstablished(Payload):
    """Signal that a robot's link to the cloud is (re)established."""

    robot: Slug
    reason: Reason | None = None


class ConnectionLost(Payload):
    """Signal that a robot's link to the cloud is severed."""

    robot: Slug
    reason: Reason | None = None


class ErrorMessage(Payload):
    """Report a processing failure or malformed input, naming the field."""

    message: Message
    field: FieldPath | None = None
    code: ErrorCode | None = None


class Shutdown(RobotScoped):
    """Order or announce a robot's permanent shutdown."""

    reason: Reason | None = None


class RobotStart(RobotScoped):
    """Order a robot to resume operating."""


class RobotStop(RobotScoped):
    """Order a robot to stop operating and stay idle."""


class RobotConfigPayload(RobotScoped):
    """Carry a robot's configuration (validated by ``bridgeos_agent.robotconfig``)."""

    config: JsonObject


class RobotConfigGet(RobotScoped):
    """Request a robot's configuration."""


class RobotConfigUpdate(RobotScoped):
    """Forward a minor runtime change to a robot's configuration."""

    changes: Annotated[dict[str, Any], Field(min_length=1, max_length=256)]


class RobotRekey(RobotScoped):
    """Give a connected robot its new token: it logs in with it from now on (its old one works for a grace)."""

    token: Token


class Offloading(RobotScoped):
    """Set or report a robot's offloading mode."""

    mode: OffloadingMode


class OffloadingGet(RobotScoped):
    """Request a robot's offloading mode."""


class SkillStart(RobotScoped):
    """Order a Skill to launch, optionally with its config and the cloud relay it uses (cloud-side routing)."""

    skill: Slug
    config: JsonObject | None = None
    cloud_relay: CloudRelayInfo | None = None


class SkillStop(RobotScoped):
    """Order a Skill to shut down."""

    skill: Slug


class SkillStatus(RobotScoped):
    """Report a Skill's lifecycle state."""

    skill: Slug
    status: SkillStatusName
    message: Message | None = None


class SkillStatusGet(RobotScoped):
    """Request a Skill's lifecycle state."""

    skill: Slug


class SkillConnect(RobotScoped):
    """Connect a Skill Manager with the Robot Controller."""

    skill: Slug
    manager_url: Url | None = None


class SkillConfigPayload(RobotScoped):
    """Carry a Skill's configuration (validated by ``bridgeos_agent.skillconfig``)."""

    skill: Slug
    config: JsonObject


class SkillConfigGet(RobotScoped):
    """Request a Skill's configuration."""

    skill: Slug


class ComponentStart(RobotScoped):
    """Order a component to launch at a location."""

    skill: Slug
    component: Slug
    location: Target


class ComponentStop(RobotScoped):
    """Order a component to shut down, at one location or wherever it runs."""

    skill: Slug
    component: Slug
    location: Target | None = None


class PullProgress(Payload):
    """Say how far the robot is in pulling a component's image (bytes of its compressed layers)."""

    image: ShortText
    done: Annotated[int, Strict(), Field(ge=0)]
    total: Annotated[int, Strict(), Field(ge=0)]


class ContainerInfo(Payload):
    """Describe the container or process running a component."""

    id: ShortText | None = None
    name: ShortText | None = None
    image: ShortText | None = None
    ip: IPvAnyAddress | None = None
    host: ShortText | None = None
    # Where peers reach it: a host name or address, and its ports, either as a list or as
    # {"<container port>": <port published on address>} (what the cloud reports for its copies).
    address: ShortText | None = None
    ports: PortList | PortMap | None = None
    pid: Annotated[int, Strict(), Field(ge=1)] | None = None
    runtime: ShortText | None = None
    namespace: ShortText | None = None
    pull: PullProgress | None = None  # while its image is being pulled, before it runs


class ComponentInformation(RobotScoped):
    """Forward the latest container details of a component."""

    skill: Slug
    component: Slug
    location: Target
    container: ContainerInfo


class ComponentStatus(RobotScoped):
    """Report a component's lifecycle state."""

    skill: Slug
    component: Slug
    status: ComponentStatusName
    location: Target | None = None
    message: Message | None = None
    # A crash's report carries the component's last lines (issue 36), so its event shows what it printed.
    last_lines: Annotated[list[LogLine], Field(max_length=CRASH_LOG_LINES)] | None = None


class ComponentStatusGet(RobotScoped):
    """Request a component's lifecycle state."""

    skill: Slug
    component: Slug


class ComponentLocation(RobotScoped):
    """Report where a component is active."""

    skill: Slug
    component: Slug
    location: Target


class ComponentMigrate(RobotScoped):
    """Order a component to move; no location means the other side."""

    skill: Slug
    component: Slug
    location: Target | None = None


# A plain dict, not a model: points are the most numerous objects the cloud holds while it ingests,
# and a dict of plain values is one the garbage collector never walks (a model instance and its
# fields-set are two it does: 30 of the 39 objects it tracked per 15-point frame).
@with_config(extra="forbid")
class MetricPoint(TypedDict):
    """Carry one measured value."""

    name: MetricName
    value: FiniteFloat
    ts: Timestamp
    skill: NotRequired[Slug | None]
    component: NotRequired[Slug | None]
    labels: NotRequired[Annotated[dict[LabelKey, LabelValue], Field(max_length=16)] | None]


class MetricsPayload(RobotScoped):
    """Forward a batch of metric points."""

    metrics: Annotated[list[MetricPoint], Field(max_length=MAX_METRICS_PER_FRAME)]


class MetricsGet(RobotScoped):
    """Request the latest values of some metrics."""

    names: Annotated[list[MetricName], Field(min_length=1, max_length=1000)] | None = None
    skill: Slug | None = None
    component: Slug | None = None
    since: Timestamp | None = None
    limit: Annotated[int, Strict(), Field(ge=1, le=MAX_METRICS_PER_FRAME)] | None = None


class MetricsSubscribe(Payload):
    """Send a client the live metrics of these robots only, instead of every robot it may see.

    Answered with ``ack``; naming a robot the client may not see (or that does not exist) is
    refused whole with ``error_message`` ``not_found``. A new connection streams every robot again.
    """

    robots: Annotated[list[Slug], Field(max_length=MAX_SUBSCRIBED_ROBOTS)]


def _relative_path(path: str) -> str:
    parts = path.split("/")
    if any(part in ("", ".", "..") for part in parts):
        raise ValueError("must be a relative path without empty, '.' or '..' parts")
    return path


# A volume file's path inside its volume: relative, "/"-separated, no empty, "." or ".." parts.
VolumePath = Annotated[str, StringConstraints(pattern=r"^[^\x00]{1,1023}$"), AfterValidator(_relative_path)]
ChunkHash = Annotated[str, StringConstraints(pattern=r"^[0-9a-f]{64}$")]
VolumeName = Annotated[str, StringConstraints(pattern=r"^[a-zA-Z0-9][a-zA-Z0-9_.-]{1,127}$")]
# Chunk data travels base64-encoded: a frame of MAX_CHUNKS_PER_FRAME chunks stays under 1 MiB.
CHUNK_BYTES = 128 * 1024
MAX_CHUNKS_PER_FRAME = 5
MAX_CHUNKS_PER_FILE = 65_536  # 8 GiB at 128 KiB


class VolumeFile(Payload):
    """Describe one changed file of a Skill volume: its new content as chunk hashes, or its deletion."""

    path: VolumePath
    deleted: bool = False
    size: Annotated[int, Strict(), Field(ge=0, le=CHUNK_BYTES * MAX_CHUNKS_PER_FILE)] = 0
    mode: Annotated[int, Strict(), Field(ge=0, le=0o7777)] = 0o644
    # sha256 of the whole content, and of each CHUNK_BYTES slice of it in order.
    hash: ChunkHash | None = None
    chunks: Annotated[list[ChunkHash], Field(max_length=MAX_CHUNKS_PER_FILE)] = Field(default_factory=list)


class VolumeChanges(RobotScoped):
    """Announce what changed in one volume of a Skill since the last announcement."""

    skill: Slug
    volume: VolumeName
    changes: Annotated[list[VolumeFile], Field(min_length=1, max_length=1000)]


class VolumeChunkRef(Payload):
    """Name one chunk by the file, its index in the file and its hash."""

    path: VolumePath
    index: Annotated[int, Strict(), Field(ge=0, lt=MAX_CHUNKS_PER_FILE)]
    hash: ChunkHash


class VolumeChunksGet(RobotScoped):
    """Ask the other side for chunks of a volume it announced."""

    skill: Slug
    volume: VolumeName
    chunks: Annotated[list[VolumeChunkRef], Field(min_length=1, max_length=MAX_CHUNKS_PER_FRAME)]


class VolumeChunk(Payload):
    """Carry one chunk's bytes, base64-encoded."""

    hash: ChunkHash
    data: Annotated[str, StringConstraints(max_length=(CHUNK_BYTES * 4) // 3 + 4)]


class VolumeChunks(RobotScoped):
    """Answer a chunk request: the chunks found, and the hashes no longer there (the file changed again)."""

    skill: Slug
    volume: VolumeName
    chunks: Annotated[list[VolumeChunk], Field(max_length=MAX_CHUNKS_PER_FRAME)] = Field(default_factory=list)
    missing: Annotated[list[ChunkHash], Field(max_length=MAX_CHUNKS_PER_FRAME)] = Field(default_factory=list)


class ComponentsApi(RobotScoped):
    """Carry a cloud copy's Components API call (thesis Table 3.2) to its Skill's manager on the robot."""

    skill: Slug
    method: Literal["GET", "POST"]
    # Only the API's own routes: /components[/ID[/location]], /metrics[/NAME].
    path: Annotated[str, StringConstraints(pattern=r"^/(components|metrics)(/[A-Za-z0-9_.-]{1,128}){0,2}$")]
    query: Annotated[str, StringConstraints(max_length=1024)] = ""
    body: JsonObject | None = None


class ComponentsApiReply(RobotScoped):
    """Carry the manager's answer to a relayed Components API call."""

    skill: Slug
    status: Annotated[int, Field(ge=100, le=599)]
    body: Any = None


class OffloadingDecision(RobotScoped):
    """Log one move a Skill Manager decided: its inputs, both costs, the prediction and the outcome."""

    skill: Slug
    component: Slug
    location: Target  # where the component ran
    target: Target  # where the decision sent it
    outcome: Literal["moved", "failed"]
    reason: Reason  # why the manager decided to move it
    error: Message | None = None  # why the move failed
    policy: ShortText
    cost_robot: FiniteFloat
    cost_cloud: FiniteFloat
    estimated_reward: FiniteFloat
    prediction: FiniteFloat | None = None
    threshold: FiniteFloat
    hysteresis: FiniteFloat
    trained: Annotated[bool, Strict()]
    samples_seen: Annotated[int, Strict(), Field(ge=0)]
    inputs: Annotated[dict[LabelKey, FiniteFloat | LabelValue], Field(max_length=32)]
    decided_at: Timestamp
    duration_s: Annotated[float, Strict(), Field(ge=0, allow_inf_nan=False)]
    # Who decided (a rule, the policy's estimate or the network that learnt outcomes) and why the network
    # was or was not trusted: its and the estimate's mean held-out error at the target location.
    decided_by: Literal["rule", "estimate", "network"] | None = None
    network_error: FiniteFloat | None = None
    estimate_error: FiniteFloat | None = None


class LogEvent(RobotScoped):
    """Carry one entry of the cloud's event log to dashboards, shaped like the REST API's events."""

    id: Annotated[int, Strict(), Field(ge=1)]
    ts: Annotated[str, StringConstraints(min_length=1, max_length=64)]  # ISO 8601, as /api/events
    level: Literal["debug", "info", "warning", "error"]
    source: ShortText
    kind: Annotated[str, StringConstraints(max_length=64)]
    skill: LabelValue
    component: LabelValue
    message: Annotated[str, StringConstraints(max_length=4000)]
    data: dict[str, Any]


# --------------------------------------------------------------------------- component logs

MAX_LOG_LINE_CHARS = 16 * 1024  # a longer line is cut there (and says so: "…[cut]")
MAX_LOG_LINES_PER_FRAME = 5000
MAX_LOG_TAIL = 1000
LOG_LEVELS = ("debug", "info", "warning", "error", "critical")
LogLevel = Literal["debug", "info", "warning", "error", "critical"]
LogStream = Literal["stdout", "stderr"]


class LogLine(Payload):
    """Carry one line a component printed: its place in its component's log, when, where and what."""

    # Counts up per component and location for as long as the robot keeps its data (restarts included):
    # (robot, skill, component, location, seq) names a line once, so a line sent twice is stored once.
    seq: Annotated[int, Strict(), Field(ge=1)]
    ts: Timestamp
    stream: LogStream
    level: LogLevel | None = None  # when the line says one (ROS's [INFO], Python logging, JSON lines)
    text: Annotated[str, StringConstraints(max_length=MAX_LOG_LINE_CHARS)]


class ComponentLogs(RobotScoped):
    """Ship, answer or push lines of one component's log, oldest first."""

    skill: Slug
    component: Slug
    location: Target = Location.ROBOT
    lines: Annotated[list[LogLine], Field(max_length=MAX_LOG_LINES_PER_FRAME)]
    # Lines of this component not shipped (over the robot's rate or byte cap, or overwritten in
    # its ring) since the previous frame: counted, never silently lost.
    dropped: Annotated[int, Strict(), Field(ge=0)] = 0


class ComponentLogsGet(RobotScoped):
    """Ask a robot for lines of its ring: those after ``after_seq`` (never shipped, say), oldest first."""

    skill: Slug
    component: Slug
    after_seq: Annotated[int, Strict(), Field(ge=0)] = 0
    limit: Annotated[int, Strict(), Field(ge=1, le=MAX_LOG_LINES_PER_FRAME)] = MAX_LOG_TAIL


class LogsSubscribe(RobotScoped):
    """Start a client's live tail of a robot, one of its Skills or one component.

    Answered by one ``component_logs`` frame per component with its last ``tail`` stored lines
    (``reply_to`` this request), then pushed ``component_logs`` frames as lines arrive. ``ring``
    also asks the robot for the lines of its ring the cloud never received.
    """

    skill: Slug | None = None
    component: Slug | None = None
    tail: Annotated[int, Strict(), Field(ge=0, le=MAX_LOG_TAIL)] = 100
    ring: bool = False

    @model_validator(mode="after")
    def _component_needs_skill(self) -> LogsSubscribe:
        if self.component is not None and self.skill is None:
            raise ValueError("a component is named within its skill: give data.skill too")
        return self


class LogsUnsubscribe(RobotScoped):
    """End a client's live tail (the same robot, skill and component it subscribed with)."""

    skill: Slug | None = None
    component: Slug | None = None


# --------------------------------------------------------------------------- recordings

RecordingId = Annotated[str, StringConstraints(pattern=r"^[0-9a-f]{32}$")]
# An absolute ROS name (ROS 1 and ROS 2 alike): "/" then letters, digits, "_" and "/".
RosTopic = Annotated[str, StringConstraints(pattern=r"^/[A-Za-z0-9_/]{1,255}$")]
MAX_RECORDING_TOPICS = 64
# MCAP bytes per chunk frame: base64 makes 256 KiB into ~350 KB, well under MAX_FRAME_BYTES.
RECORDING_CHUNK_BYTES = 256 * 1024
MIN_RECORDING_BYTES = 1024
MAX_RECORDING_BYTES = 4 * 1024**3
MAX_RECORDING_DURATION_S = 86_400.0


class RecordingStatusName(enum.StrEnum):
    """Name the states of a recording, as the robot reports them and the cloud keeps them."""

    STARTING = "starting"
    RECORDING = "recording"
    STOPPING = "stopping"
    FINISHED = "finished"
    FAILED = "failed"


class RecordingStart(RobotScoped):
    """Order a robot to record topics of its ROS 1 or ROS 2 graph into MCAP, within limits."""

    recording: RecordingId
    topics: Annotated[list[RosTopic], Field(min_length=1, max_length=MAX_RECORDING_TOPICS)]
    # Which graph: "ros1", "ros2", or None for the one that has every topic.
    ros: Literal["ros1", "ros2"] | None = None
    # Message bytes recorded at most, and seconds: reaching either ends the recording cleanly.
    max_bytes: Annotated[int, Strict(), Field(ge=MIN_RECORDING_BYTES, le=MAX_RECORDING_BYTES)]
    max_duration_s: Annotated[float, Field(gt=0, le=MAX_RECORDING_DURATION_S, allow_inf_nan=False)]


class RecordingStop(RobotScoped):
    """Order a robot to end a recording."""

    recording: RecordingId


class RecordingChunk(RobotScoped):
    """Carry the next bytes of a recording's MCAP file, base64-encoded; ``seq`` counts from 0."""

    recording: RecordingId
    seq: Annotated[int, Strict(), Field(ge=0, le=MAX_RECORDING_BYTES // RECORDING_CHUNK_BYTES + 1)]
    data: Annotated[str, StringConstraints(min_length=1, max_length=(RECORDING_CHUNK_BYTES * 4) // 3 + 4)]


class UpdateHold(RobotScoped):
    """Hold the robot's updates for ``seconds`` at most (a busy component); 0 releases its hold."""

    skill: Slug
    component: Slug
    seconds: Annotated[float, Field(ge=0, le=MAX_HOLD_S, allow_inf_nan=False)]
    reason: Annotated[str, StringConstraints(max_length=500)] = ""


class RecordingStatus(RobotScoped):
    """Report a recording's state; ``finished`` and ``failed`` carry its totals and how many chunks it has."""

    recording: RecordingId
    status: RecordingStatusName
    ros: Literal["ros1", "ros2"] | None = None
    message: Message | None = None
    started_at: Timestamp | None = None
    stopped_at: Timestamp | None = None
    messages: Annotated[int, Strict(), Field(ge=0)] = 0
    bytes: Annotated[int, Strict(), Field(ge=0)] = 0
    chunks: Annotated[int, Strict(), Field(ge=0)] | None = None


class Ack(Payload):
    """Acknowledge the frame named by the envelope's ``reply_to``."""


# --------------------------------------------------------------------------- bridges
# A client of /ws/rosbridge/<robot>/ or /ws/foxglove/<robot>/ is one bridge session on the robot's
# own link: the cloud opens it, both sides carry its WebSocket frames, either side closes it. Live
# data, so none is acked or resent: a session dies with the link and its client reconnects.

BRIDGE_KINDS = ("rosbridge", "foxglove")
# A client frame larger than this crosses the link in parts (``more``), so an envelope stays well
# under MAX_FRAME_BYTES even when JSON escaping multiplies a text part's size.
BRIDGE_PART_CHARS = 128 * 1024
BRIDGE_BINARY_CHARS = (BRIDGE_PART_CHARS * 4) // 3 + 4  # a binary part's base64
BridgeSessionId = Annotated[str, StringConstraints(pattern=r"^[A-Za-z0-9_-]{8,64}$")]

# A large frame that several clients receive (a point cloud to ten viewers) crosses the link once,
# as binary WebSocket messages of its own (a blob, in parts of at most BRIDGE_BLOB_PART_BYTES), not
# once per client in base64: each client's bridge_frame then names the blob, behind a few bytes of
# its own (Foxglove's subscription id and time). The cloud keeps a robot's latest blobs, oldest out
# first, within a BlobWindow; the agent keeps the same window's account, so it knows which blobs
# the cloud still holds and sends again one that has left it.
BRIDGE_BLOB_MAGIC = b"\xb1BOB"
BRIDGE_BLOB_MIN_BYTES = 64 * 1024  # smaller frames travel inline (batched), as before
BRIDGE_BLOB_PART_BYTES = 1 << 20  # a binary message of the link, under the transport's 2 MiB ceiling
BRIDGE_BLOB_MAX_BYTES = 16 << 20
BRIDGE_BLOB_WINDOW_BYTES = 24 << 20
BRIDGE_BLOB_WINDOW_COUNT = 64
BRIDGE_HEAD_BYTES = 64  # the most of a client's own bytes in front of a blob
_BLOB_HEAD = struct.Struct("<4sIB")  # magic, blob id, flags
_BLOB_TEXT = 1  # UTF-8 text, sent to its clients as text frames
_BLOB_MORE = 2  # more parts of this blob follow


class BlobWindow:
    """Which blobs the cloud holds of one robot's link: the latest, within a count and a byte size."""

    def __init__(self, count: int = BRIDGE_BLOB_WINDOW_COUNT, size: int = BRIDGE_BLOB_WINDOW_BYTES) -> None:
        self.count = count
        self.size = size
        self.held: OrderedDict[int, int] = OrderedDict()  # blob id -> bytes, oldest first
        self.bytes = 0

    def add(self, blob: int, size: int) -> list[int]:
        """Hold a new blob; return the blobs it pushed out, oldest first (never the new one)."""
        if blob in self.held:
            self.bytes -= self.held.pop(blob)
        self.held[blob] = size
        self.bytes += size
        gone = []
        while len(self.held) > 1 and (len(self.held) > self.count or self.bytes > self.size):
            old, old_size = self.held.popitem(last=False)
            self.bytes -= old_size
            gone.append(old)
        return gone

    def clear(self) -> None:
        """Forget every blob (the link they were sent on is gone)."""
        self.held.clear()
        self.bytes = 0


def encode_bridge_blob(blob: int, data: bytes | bytearray | memoryview | str) -> list[bytes]:
    """Encode a blob as the binary messages of the robot's link that carry it, in order."""
    text = isinstance(data, str)
    body = memoryview(data.encode("utf-8", "surrogatepass") if isinstance(data, str) else data).cast("B")
    if len(body) > BRIDGE_BLOB_MAX_BYTES:
        raise ValueError(f"a bridge blob may carry at most {BRIDGE_BLOB_MAX_BYTES} bytes")
    step = BRIDGE_BLOB_PART_BYTES
    messages = []
    for start in range(0, max(len(body), 1), step):
        flags = (_BLOB_TEXT if text else 0) | (_BLOB_MORE if start + step < len(body) else 0)
        messages.append(b"".join((_BLOB_HEAD.pack(BRIDGE_BLOB_MAGIC, blob, flags), body[start : start + step])))
    return messages


def is_bridge_blob(message: bytes) -> bool:
    """Tell whether a binary message of the robot's link carries (part of) a blob."""
    return message[:4] == BRIDGE_BLOB_MAGIC


def decode_bridge_blob(message: bytes) -> tuple[int, bool, bool, bytes]:
    """Return a blob message's blob id, whether it is text, whether more parts follow, and its bytes.

    ProtocolError: not a blob message, or a part larger than BRIDGE_BLOB_PART_BYTES.
    """
    if len(message) < _BLOB_HEAD.size or not is_bridge_blob(message):
        raise ProtocolError("not a bridge blob", code="invalid_frame")
    if len(message) - _BLOB_HEAD.size > BRIDGE_BLOB_PART_BYTES:
        raise ProtocolError(f"a bridge blob part may carry at most {BRIDGE_BLOB_PART_BYTES} bytes", code="too_large")
    _, blob, flags = _BLOB_HEAD.unpack_from(message)
    if flags & ~(_BLOB_TEXT | _BLOB_MORE):
        raise ProtocolError(f"unknown bridge blob flags {flags}", code="invalid_frame")
    return blob, bool(flags & _BLOB_TEXT), bool(flags & _BLOB_MORE), message[_BLOB_HEAD.size :]


class BridgeOpen(Payload):
    """Open a bridge session of a kind for one client, sending at most ``bytes_per_s`` to it."""

    session: BridgeSessionId
    kind: Literal["rosbridge", "foxglove"]
    bytes_per_s: Annotated[int, Strict(), Field(ge=1024)] | None = None
    # The cloud takes several whole frames in one bridge_frame (``texts``/``binaries``); an agent
    # that is not told so sends one frame per bridge_frame.
    batches: bool = False
    # The cloud takes blobs (binary messages of the link) and bridge_frames naming them.
    blobs: bool = False


class BridgeFrame(Payload):
    """Carry (a part of) one WebSocket frame of a bridge session, or several whole ones in order.

    One of: ``text``; ``binary`` in base64; ``texts``, whole text frames; ``binaries``, whole
    binary frames in base64; ``blob``, a whole frame sent before as a blob, behind its ``head``.
    Batches (only to a cloud that opened the session with ``batches``) spare a busy topic one
    envelope per message; their frames together stay within one part's size.
    """

    session: BridgeSessionId
    text: Annotated[str, StringConstraints(max_length=BRIDGE_PART_CHARS)] | None = None
    binary: Annotated[str, StringConstraints(max_length=BRIDGE_BINARY_CHARS)] | None = None
    texts: Annotated[list[str], Field(min_length=1)] | None = None
    binaries: Annotated[list[str], Field(min_length=1)] | None = None
    blob: Annotated[int, Strict(), Field(ge=0, lt=1 << 32)] | None = None
    # The client's own bytes in front of the blob, in base64 (binary blobs only).
    head: Annotated[str, StringConstraints(max_length=(BRIDGE_HEAD_BYTES * 4) // 3 + 4)] | None = None
    more: bool = False  # more parts of this frame follow
    # Messages the robot dropped for this client since its last report (its queues were full).
    dropped: Annotated[int, Strict(), Field(ge=0)] | None = None

    @model_validator(mode="after")
    def _one_kind(self) -> BridgeFrame:
        kinds = (self.text, self.binary, self.texts, self.binaries, self.blob)
        if sum(kind is not None for kind in kinds) != 1:
            raise ValueError(
                "a bridge frame carries exactly one of text, binary and blob (or a batch: texts or binaries)"
            )
        if self.head is not None and self.blob is None:
            raise ValueError("only a frame naming a blob has a head")
        if self.blob is not None and self.more:
            raise ValueError("a frame naming a blob is whole (no 'more')")
        batch = self.texts if self.texts is not None else self.binaries
        if batch is not None:
            if self.more:
                raise ValueError("a batch of bridge frames carries whole frames only (no 'more')")
            limit = BRIDGE_PART_CHARS if self.texts is not None else BRIDGE_BINARY_CHARS
            if sum(len(frame) for frame in batch) > limit:
                raise ValueError(f"a batch of bridge frames may carry at most {limit} characters")
        return self


class BridgeClose(Payload):
    """End a bridge session, saying why (told to its client)."""

    session: BridgeSessionId
    reason: Annotated[str, StringConstraints(max_length=500)] = ""


PAYLOADS: Mapping[str, type[Payload]] = {
    Event.AUTHENTICATION_CLIENT: AuthenticationClient,
    Event.AUTHENTICATION_ROBOT: AuthenticationRobot,
    Event.AUTHENTICATION_SUCCESS: AuthenticationSuccess,
    Event.AUTHENTICATION_FAILURE: AuthenticationFailure,
    Event.CONNECTION_ESTABLISHED: ConnectionEstablished,
    Event.CONNECTION_LOST: ConnectionLost,
    Event.ERROR_MESSAGE: ErrorMessage,
    Event.SHUTDOWN: Shutdown,
    Event.ROBOT_START: RobotStart,
    Event.ROBOT_STOP: RobotStop,
    Event.ROBOT_CONFIG: RobotConfigPayload,
    Event.ROBOT_CONFIG_GET: RobotConfigGet,
    Event.ROBOT_CONFIG_UPDATE: RobotConfigUpdate,
    Event.OFFLOADING: Offloading,
    Event.OFFLOADING_GET: OffloadingGet,
    Event.SKILL_START: SkillStart,
    Event.SKILL_STOP: SkillStop,
    Event.SKILL_STATUS: SkillStatus,
    Event.SKILL_STATUS_GET: SkillStatusGet,
    Event.SKILL_CONNECT: SkillConnect,
    Event.SKILL_CONFIG: SkillConfigPayload,
    Event.SKILL_CONFIG_GET: SkillConfigGet,
    Event.COMPONENT_START: ComponentStart,
    Event.COMPONENT_STOP: ComponentStop,
    Event.COMPONENT_INFORMATION: ComponentInformation,
    Event.COMPONENT_STATUS: ComponentStatus,
    Event.COMPONENT_STATUS_GET: ComponentStatusGet,
    Event.COMPONENT_LOCATION: ComponentLocation,
    Event.COMPONENT_MIGRATE: ComponentMigrate,
    Event.METRICS: MetricsPayload,
    Event.METRICS_GET: MetricsGet,
    Event.VOLUME_CHANGES: VolumeChanges,
    Event.VOLUME_CHUNKS_GET: VolumeChunksGet,
    Event.VOLUME_CHUNKS: VolumeChunks,
    Event.ACK: Ack,
    Event.OFFLOADING_DECISION: OffloadingDecision,
    Event.COMPONENTS_API: ComponentsApi,
    Event.COMPONENTS_API_REPLY: ComponentsApiReply,
    Event.LOG_EVENT: LogEvent,
    Event.BRIDGE_OPEN: BridgeOpen,
    Event.BRIDGE_FRAME: BridgeFrame,
    Event.BRIDGE_CLOSE: BridgeClose,
    # recordings
    Event.RECORDING_START: RecordingStart,
    Event.RECORDING_STOP: RecordingStop,
    Event.RECORDING_CHUNK: RecordingChunk,
    Event.RECORDING_STATUS: RecordingStatus,
    Event.UPDATE_HOLD: UpdateHold,
    Event.ROBOT_REKEY: RobotRekey,
    # component logs
    Event.COMPONENT_LOGS: ComponentLogs,
    Event.COMPONENT_LOGS_GET: ComponentLogsGet,
    Event.LOGS_SUBSCRIBE: LogsSubscribe,
    Event.LOGS_UNSUBSCRIBE: LogsUnsubscribe,
    Event.METRICS_SUBSCRIBE: MetricsSubscribe,
}


# --------------------------------------------------------------------------- classification

_R2C, _C2R = Direction.ROBOT_TO_CLOUD, Direction.CLOUD_TO_ROBOT
_K2C, _C2K = Direction.CLIENT_TO_CLOUD, Direction.CLOUD_TO_CLIENT
_ALL = frozenset(Direction)

# Clients reach robots only through the cloud, which relays commands (client→cloud→robot)
# and mirrors what robots report to dashboards (robot→cloud→client).
DIRECTIONS: Mapping[str, frozenset[Direction]] = {
    Event.AUTHENTICATION_CLIENT: frozenset({_K2C}),
    Event.AUTHENTICATION_ROBOT: frozenset({_R2C}),
    Event.AUTHENTICATION_SUCCESS: frozenset({_C2R, _C2K}),
    Event.AUTHENTICATION_FAILURE: frozenset({_C2R, _C2K}),
    Event.CONNECTION_ESTABLISHED: frozenset({_C2R, _C2K}),
    Event.CONNECTION_LOST: frozenset({_C2K}),
    Event.ERROR_MESSAGE: _ALL,
    Event.SHUTDOWN: _ALL,
    Event.ROBOT_START: frozenset({_K2C, _C2R, _C2K}),
    Event.ROBOT_STOP: frozenset({_K2C, _C2R, _C2K}),
    Event.ROBOT_CONFIG: frozenset({_C2R, _C2K}),
    Event.ROBOT_CONFIG_GET: frozenset({_R2C, _K2C}),
    Event.ROBOT_CONFIG_UPDATE: frozenset({_K2C, _C2R, _C2K}),
    Event.OFFLOADING: _ALL,
    Event.OFFLOADING_GET: frozenset({_K2C, _C2R}),
    Event.SKILL_START: frozenset({_K2C, _C2R, _C2K}),
    Event.SKILL_STOP: frozenset({_K2C, _C2R, _C2K}),
    Event.SKILL_STATUS: frozenset({_R2C, _C2K}),
    Event.SKILL_STATUS_GET: frozenset({_K2C, _C2R}),
    Event.SKILL_CONNECT: frozenset({_R2C, _C2K}),
    Event.SKILL_CONFIG: frozenset({_R2C, _C2R, _C2K}),
    Event.SKILL_CONFIG_GET: frozenset({_R2C, _K2C, _C2R}),
    # A robot's controller forwards cloud-side launches to the cloud (thesis §3.2.2).
    Event.COMPONENT_START: _ALL,
    Event.COMPONENT_STOP: _ALL,
    Event.COMPONENT_INFORMATION: frozenset({_R2C, _C2R, _C2K}),
    Event.COMPONENT_STATUS: frozenset({_R2C, _C2R, _C2K}),
    Event.COMPONENT_STATUS_GET: frozenset({_R2C, _K2C, _C2R}),
    Event.COMPONENT_LOCATION: frozenset({_R2C, _C2K}),
    Event.COMPONENT_MIGRATE: frozenset({_K2C, _C2R, _C2K}),
    # The cloud sends a robot the stats of its cloud components too.
    Event.METRICS: frozenset({_R2C, _C2R, _C2K}),
    Event.METRICS_GET: frozenset({_K2C, _C2R}),
    Event.VOLUME_CHANGES: frozenset({_R2C, _C2R}),
    Event.VOLUME_CHUNKS_GET: frozenset({_R2C, _C2R}),
    Event.VOLUME_CHUNKS: frozenset({_R2C, _C2R}),
    Event.ACK: _ALL,
    Event.OFFLOADING_DECISION: frozenset({_R2C, _C2K}),
    Event.COMPONENTS_API: frozenset({_C2R}),
    Event.COMPONENTS_API_REPLY: frozenset({_R2C}),
    Event.LOG_EVENT: frozenset({_C2K}),
    Event.BRIDGE_OPEN: frozenset({_C2R}),
    Event.BRIDGE_FRAME: frozenset({_R2C, _C2R}),
    Event.BRIDGE_CLOSE: frozenset({_R2C, _C2R}),
    # recordings
    Event.RECORDING_START: frozenset({_C2R}),
    Event.RECORDING_STOP: frozenset({_C2R}),
    Event.RECORDING_CHUNK: frozenset({_R2C}),
    Event.RECORDING_STATUS: frozenset({_R2C}),
    Event.UPDATE_HOLD: frozenset({_R2C}),
    Event.ROBOT_REKEY: frozenset({_C2R}),
    # component logs: robots ship and answer them, clients subscribe and are pushed them
    Event.COMPONENT_LOGS: frozenset({_R2C, _C2K}),
    Event.COMPONENT_LOGS_GET: frozenset({_C2R}),
    Event.LOGS_SUBSCRIBE: frozenset({_K2C}),
    Event.LOGS_UNSUBSCRIBE: frozenset({_K2C}),
    Event.METRICS_SUBSCRIBE: frozenset({_K2C}),
}

# Events that change state: the receiver acks them, the sender retransmits until it does,
# and the receiver applies each id once.
REQUIRES_ACK: frozenset[Event] = frozenset(
    {
        Event.CONNECTION_ESTABLISHED,
        Event.CONNECTION_LOST,
        Event.SHUTDOWN,
        Event.ROBOT_START,
        Event.ROBOT_STOP,
        Event.ROBOT_CONFIG,
        Event.ROBOT_CONFIG_UPDATE,
        Event.OFFLOADING,
        Event.SKILL_START,
        Event.SKILL_STOP,
        Event.SKILL_STATUS,
        Event.SKILL_CONNECT,
        Event.SKILL_CONFIG,
        Event.COMPONENT_START,
        Event.COMPONENT_STOP,
        Event.COMPONENT_INFORMATION,
        Event.COMPONENT_STATUS,
        Event.COMPONENT_LOCATION,
        Event.COMPONENT_MIGRATE,
        Event.METRICS,
        Event.VOLUME_CHANGES,
        Event.OFFLOADING_DECISION,
        # recordings
        Event.RECORDING_START,
        Event.RECORDING_STOP,
        Event.RECORDING_CHUNK,
        Event.RECORDING_STATUS,
        Event.ROBOT_REKEY,
        Event.UPDATE_HOLD,
        # a shipped batch stays unshipped in the robot's ring until acked
        Event.COMPONENT_LOGS,
    }
)

# Orders whose outcome the sender awaits: ``ack`` once accepted, ``error_message`` if refused.
COMMANDS: frozenset[Event] = frozenset(
    {
        Event.SHUTDOWN,
        Event.ROBOT_START,
        Event.ROBOT_STOP,
        Event.ROBOT_CONFIG_UPDATE,
        Event.OFFLOADING,
        Event.SKILL_START,
        Event.SKILL_STOP,
        Event.COMPONENT_START,
        Event.COMPONENT_STOP,
        Event.COMPONENT_MIGRATE,
        # recordings
        Event.RECORDING_START,
        Event.RECORDING_STOP,
        # acked once the robot keeps its new token (in its token file, when it has one)
        Event.ROBOT_REKEY,
    }
)

_COMMAND_REPLIES = frozenset({Event.ACK, Event.ERROR_MESSAGE})
_AUTH_REPLIES = frozenset({Event.AUTHENTICATION_SUCCESS, Event.AUTHENTICATION_FAILURE})


def _answered_by(event: Event) -> frozenset[Event]:
    return frozenset({event, Event.ERROR_MESSAGE})


# Requests and the events that may answer them (carrying ``reply_to`` = the request id).
REPLIES: Mapping[str, frozenset[Event]] = {
    Event.AUTHENTICATION_CLIENT: _AUTH_REPLIES,
    Event.AUTHENTICATION_ROBOT: _AUTH_REPLIES,
    Event.ROBOT_CONFIG_GET: _answered_by(Event.ROBOT_CONFIG),
    Event.OFFLOADING_GET: _answered_by(Event.OFFLOADING),
    Event.SKILL_STATUS_GET: _answered_by(Event.SKILL_STATUS),
    Event.SKILL_CONFIG_GET: _answered_by(Event.SKILL_CONFIG),
    Event.COMPONENT_STATUS_GET: _answered_by(Event.COMPONENT_STATUS),
    Event.METRICS_GET: _answered_by(Event.METRICS),
    Event.VOLUME_CHUNKS_GET: _answered_by(Event.VOLUME_CHUNKS),
    Event.COMPONENTS_API: _answered_by(Event.COMPONENTS_API_REPLY),
    Event.COMPONENT_LOGS_GET: _answered_by(Event.COMPONENT_LOGS),
    Event.LOGS_SUBSCRIBE: _answered_by(Event.COMPONENT_LOGS),
    Event.LOGS_UNSUBSCRIBE: frozenset({Event.ACK, Event.ERROR_MESSAGE}),
    Event.METRICS_SUBSCRIBE: frozenset({Event.ACK, Event.ERROR_MESSAGE}),
    **{command: _COMMAND_REPLIES for command in COMMANDS},
}


def is_allowed(event: Event | str, direction: Direction | str) -> bool:
    """Tell whether ``event`` may travel in ``direction``."""
    try:
        return Direction(direction) in DIRECTIONS[Event(event)]
    except ValueError:
        return False


# --------------------------------------------------------------------------- errors


class ProtocolError(ValueError):
    """Reject a frame, naming the offending field and a machine-readable code."""

    def __init__(self, message: str, *, field: str | None = None, code: str = "invalid_frame"):
        super().__init__(f"{field}: {message}" if field else message)
        self.message = message
        self.field = field
        self.code = code

    def to_payload(self) -> ErrorMessage:
        """Describe this error as an ``error_message`` payload."""
        return ErrorMessage(
            message=str(self)[:2000] or self.code,
            field=self.field[:256] if self.field else None,
            code=self.code,
        )


def _field_path(prefix: str | None, loc: tuple[int | str, ...]) -> str | None:
    parts = [prefix] if prefix else []
    parts.extend(str(part) for part in loc)
    return ".".join(parts) or None


def _from_validation_error(exc: ValidationError, *, prefix: str | None, code: str) -> ProtocolError:
    errors = exc.errors(include_url=False, include_context=False, include_input=False)
    first = errors[0]
    if first["type"] == "json_invalid":
        return ProtocolError(first["msg"], code="invalid_json")
    if first["type"] in {"model_type", "dict_type"} and not first["loc"]:
        return ProtocolError("frame must be a JSON object", code="not_object")
    if first["type"] == "string_unicode" and not first["loc"]:
        return ProtocolError("frame is not valid UTF-8 text", code="invalid_json")
    message = first["msg"]
    if len(errors) > 1:
        message += f" (and {len(errors) - 1} more error{'s' if len(errors) > 2 else ''})"
    return ProtocolError(message, field=_field_path(prefix, first["loc"]), code=code)


# --------------------------------------------------------------------------- envelope


class Envelope(BaseModel):
    """Wrap every frame: which event, its id, what it answers, its payload, when sent."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    # Kept as a plain string here so an unknown event gets its own clear error in decode().
    event: Annotated[str, StringConstraints(min_length=1, max_length=64)]
    id: MessageId
    reply_to: MessageId | None = None
    data: dict[str, Any] = Field(default_factory=dict)
    # Optional on input because outside clients may omit it; 0 then means "unknown".
    ts: Timestamp = 0.0

    # A plain slot, not a PrivateAttr: pydantic's private-attribute setup would cost more
    # per decoded frame than validating the envelope itself.
    __slots__ = ("_validated",)

    @property
    def kind(self) -> Event:
        """Return the event as an ``Event`` member."""
        return Event(self.event)


# --------------------------------------------------------------------------- ids


class IdGenerator:
    """Generate short unique frame ids: a random per-process prefix and a counter."""

    def __init__(self, prefix: str | None = None):
        self._prefix = prefix if prefix is not None else os.urandom(6).hex()
        self._counter = itertools.count(1)

    def __call__(self) -> str:
        """Return the next id."""
        return f"{self._prefix}-{next(self._counter):x}"

    def reseed(self) -> None:
        """Pick a fresh random prefix, e.g. in a forked child."""
        self._prefix = os.urandom(6).hex()
        self._counter = itertools.count(1)


new_id = IdGenerator()
# A forked worker would otherwise repeat its parent's ids, and the receiver drop them as dups.
os.register_at_fork(after_in_child=new_id.reseed)


# --------------------------------------------------------------------------- codec


def encode(envelope: Envelope) -> str:
    """Serialise an envelope to compact JSON text."""
    return envelope.model_dump_json()


def as_json_data(envelope: Envelope) -> dict[str, Any]:
    """Return an envelope as the JSON data ``encode`` writes, without the text in between."""
    return envelope.model_dump(mode="json")


def decode(
    text: str | bytes | bytearray,
    *,
    max_bytes: int = MAX_FRAME_BYTES,
    direction: Direction | None = None,
) -> Envelope:
    """Parse and validate a frame and its payload, raising only ``ProtocolError``."""
    if not isinstance(text, (str, bytes, bytearray)):
        raise ProtocolError(f"frame must be text or bytes, not {type(text).__name__}", code="invalid_type")
    size = len(text)
    # A UTF-8 char takes at most 4 bytes, so str needs an exact count only near the limit.
    if isinstance(text, str) and size * 4 > max_bytes:
        size = len(text.encode("utf-8", "surrogatepass"))
    if size > max_bytes:
        raise ProtocolError(f"frame of {size} bytes exceeds the limit of {max_bytes} bytes", code="too_large")
    try:
        envelope = Envelope.model_validate_json(text)
    except ValidationError as exc:
        raise _from_validation_error(exc, prefix=None, code="invalid_envelope") from None
    except (ValueError, TypeError, RecursionError) as exc:
        raise ProtocolError(f"unreadable frame: {exc}"[:500], code="invalid_json") from None
    _check(envelope, direction)
    object.__setattr__(envelope, "_validated", _validate_payload(envelope.event, envelope.data))
    return envelope


def _check(envelope: Envelope, direction: Direction | None) -> None:
    if envelope.event not in EVENTS:
        raise ProtocolError(f"unknown event {envelope.event[:64]!r}", field="event", code="unknown_event")
    if envelope.event == Event.ACK and envelope.reply_to is None:
        raise ProtocolError("an ack must name the acknowledged id", field="reply_to", code="invalid_envelope")
    if direction is not None and direction not in DIRECTIONS[envelope.event]:
        raise ProtocolError(
            f"event {envelope.event!r} is not allowed {Direction(direction).value.replace('_', ' ')}",
            field="event",
            code="forbidden_event",
        )


def _validate_payload(event: str, data: Any) -> Payload:
    try:
        return PAYLOADS[event].model_validate(data)
    except ValidationError as exc:
        raise _from_validation_error(exc, prefix="data", code="invalid_payload") from None
    except (ValueError, TypeError, RecursionError) as exc:
        raise ProtocolError(f"unreadable payload: {exc}"[:500], field="data", code="invalid_payload") from None


def parse_payload(envelope: Envelope) -> Payload:
    """Return the envelope's payload as its event's model, validating it once."""
    payload: Payload | None = getattr(envelope, "_validated", None)
    if payload is None:
        _check(envelope, None)
        payload = _validate_payload(envelope.event, envelope.data)
        object.__setattr__(envelope, "_validated", payload)
    return payload


def make(
    event: Event | str,
    data: Payload | Mapping[str, Any] | None = None,
    *,
    reply_to: str | None = None,
    id: str | None = None,
    now: float,
) -> Envelope:
    """Build a validated envelope for ``event``; raise ``ProtocolError`` on bad input."""
    if event not in EVENTS:
        raise ProtocolError(f"unknown event {str(event)[:64]!r}", field="event", code="unknown_event")
    model = PAYLOADS[Event(event)]
    payload = data if isinstance(data, model) else _validate_payload(event, dict(data or {}))
    try:
        envelope = Envelope(
            event=Event(event).value,
            id=id if id is not None else new_id(),
            reply_to=reply_to,
            data=payload.model_dump(mode="json", exclude_none=True),
            ts=float(now),
        )
    except ValidationError as exc:
        raise _from_validation_error(exc, prefix=None, code="invalid_envelope") from None
    _check(envelope, None)
    object.__setattr__(envelope, "_validated", payload)
    return envelope


def ack_frame(envelope_id: str, *, now: float, id: str | None = None) -> Envelope:
    """Build the ``ack`` for the frame with ``envelope_id``."""
    return make(Event.ACK, reply_to=envelope_id, id=id, now=now)


def ack_text(envelope_id: str, *, now: float) -> str:
    """Encode the ``ack`` of a decoded frame as text, skipping validation on this hot path.

    ``envelope_id`` must come from a decoded envelope, whose id pattern leaves nothing to escape.
    """
    return f'{{"event":"ack","id":"{new_id()}","reply_to":"{envelope_id}","data":{{}},"ts":{float(now)!r}}}'


def error_frame(exc: BaseException, reply_to: str | None = None, *, now: float, id: str | None = None) -> Envelope:
    """Build an ``error_message`` describing ``exc``, answering ``reply_to``."""
    if isinstance(exc, ValidationError):
        exc = _from_validation_error(exc, prefix="data", code="invalid_payload")
    if isinstance(exc, ProtocolError):
        payload = exc.to_payload()
    else:
        payload = ErrorMessage(message=(str(exc) or type(exc).__name__)[:2000], code="internal_error")
    # The frame being refused may carry a malformed id; answer anyway rather than fail twice.
    if reply_to is not None and not _ID_RE.fullmatch(reply_to):
        reply_to = None
    return make(Event.ERROR_MESSAGE, payload, reply_to=reply_to, id=id, now=now)


# --------------------------------------------------------------------------- reliability


@dataclass(slots=True)
class Pending:
    """Track one unacknowledged frame."""

    envelope: Envelope
    seq: int
    attempts: int
    first_sent: float
    next_at: float


class Reliable:
    """Retransmit state-changing frames with capped exponential backoff until acked.

    It never gives up: the robot may be offline for hours and its reports must still
    arrive. ``attempts`` is exposed so callers can surface a stuck peer.
    """

    def __init__(
        self,
        *,
        initial: float = 1.0,
        factor: float = 2.0,
        cap: float = 30.0,
        jitter: float = 0.1,
        random: Callable[[], float] = _random.random,
    ):
        self.initial = initial
        self.factor = factor
        self.cap = cap
        self.jitter = jitter
        self._random = random
        self._pending: dict[str, Pending] = {}
        self._heap: list[tuple[float, int, str]] = []
        self._seq = itertools.count()

    def _delay(self, attempts: int) -> float:
        base = min(self.cap, self.initial * self.factor ** min(attempts - 1, 64))
        # Jitter spreads a fleet's retries after a cloud restart; centred on 0.5 so a fake
        # random of 0.5 gives the exact schedule.
        spread = 1.0 + self.jitter * (2.0 * self._random() - 1.0)
        return min(self.cap, base * spread)

    def send(self, envelope: Envelope, now: float) -> bool:
        """Register a sent frame; return whether it awaits an ack."""
        if envelope.event not in REQUIRES_ACK:
            return False
        if envelope.id not in self._pending:
            entry = Pending(envelope, next(self._seq), 1, now, now + self._delay(1))
            self._pending[envelope.id] = entry
            heapq.heappush(self._heap, (entry.next_at, entry.seq, envelope.id))
        return True

    def on_ack(self, reply_to: str | None) -> bool:
        """Forget the acknowledged frame; return whether it was pending."""
        return reply_to is not None and self._pending.pop(reply_to, None) is not None

    def due(self, now: float) -> list[Envelope]:
        """Return frames to retransmit now, in send order, and schedule their next try."""
        fired: list[Pending] = []
        heap = self._heap
        while heap and heap[0][0] <= now:
            next_at, seq, frame_id = heapq.heappop(heap)
            entry = self._pending.get(frame_id)
            if entry is None or entry.seq != seq or entry.next_at != next_at:
                continue
            fired.append(entry)
        fired.sort(key=lambda entry: entry.seq)
        for entry in fired:
            entry.attempts += 1
            entry.next_at = now + self._delay(entry.attempts)
            heapq.heappush(heap, (entry.next_at, entry.seq, entry.envelope.id))
        return [entry.envelope for entry in fired]

    def resend_all(self, now: float) -> list[Envelope]:
        """Make every pending frame due now, e.g. after a reconnect, and return them."""
        for entry in self._pending.values():
            entry.next_at = now
        self._heap = [(now, entry.seq, frame_id) for frame_id, entry in self._pending.items()]
        return self.due(now)

    def next_due(self) -> float | None:
        """Return when the earliest retransmission falls due, if any."""
        while self._heap:
            next_at, seq, frame_id = self._heap[0]
            entry = self._pending.get(frame_id)
            if entry is not None and entry.seq == seq and entry.next_at == next_at:
                return next_at
            heapq.heappop(self._heap)
        return None

    def pending(self) -> list[Envelope]:
        """Return unacknowledged frames in send order."""
        return [entry.envelope for entry in self._pending.values()]

    def attempts(self, frame_id: str) -> int:
        """Return how many times a pending frame has been sent (0 if not pending)."""
        entry = self._pending.get(frame_id)
        return entry.attempts if entry else 0

    def __len__(self) -> int:
        return len(self._pending)

    def __contains__(self, frame_id: object) -> bool:
        return frame_id in self._pending


class Dedup:
    """Remember the last ``capacity`` frame ids so a retransmitted frame is applied once."""

    def __init__(self, capacity: int = 10_000, ids: Iterable[str] = ()):
        if capacity < 1:
            raise ValueError("capacity must be at least 1")
        self.capacity = capacity
        self._ids: OrderedDict[str, None] = OrderedDict()
        self.load(ids)

    def seen(self, frame_id: str) -> bool:
        """Mark ``frame_id``; return True if it was already marked (a duplicate)."""
        ids = self._ids
        if frame_id in ids:
            ids.move_to_end(frame_id)
            return True
        ids[frame_id] = None
        if len(ids) > self.capacity:
            ids.popitem(last=False)
        return False

    def forget(self, frame_id: str) -> None:
        """Unmark ``frame_id`` so a retransmission is applied after a failed attempt."""
        self._ids.pop(frame_id, None)

    def export(self) -> list[str]:
        """Return the remembered ids, oldest first, for persisting."""
        return list(self._ids)

    def load(self, ids: Iterable[str]) -> None:
        """Mark persisted ids (oldest first) as seen."""
        for frame_id in ids:
            self.seen(frame_id)

    def __len__(self) -> int:
        return len(self._ids)

    def __contains__(self, frame_id: object) -> bool:
        return frame_id in self._ids


class Correlator:
    """Match replies to outstanding requests by ``reply_to`` and expire the unanswered."""

    def __init__(self) -> None:
        self._deadlines: dict[str, float] = {}
        self._heap: list[tuple[float, str]] = []

    def expect(self, request_id: str, now: float, timeout: float) -> None:
        """Await a reply to ``request_id`` until ``now + timeout``."""
        deadline = now + timeout
        self._deadlines[request_id] = deadline
        heapq.heappush(self._heap, (deadline, request_id))

    def resolve(self, reply: Envelope) -> bool:
        """Close the request ``reply`` answers; return whether one was outstanding."""
        return reply.reply_to is not None and self._deadlines.pop(reply.reply_to, None) is not None

    def expired(self, now: float) -> list[str]:
        """Drop and return requests whose deadline passed, oldest deadline first."""
        gone: list[str] = []
        heap = self._heap
        while heap and heap[0][0] <= now:
            deadline, request_id = heapq.heappop(heap)
            if self._deadlines.get(request_id) == deadline:
                del self._deadlines[request_id]
                gone.append(request_id)
        return gone

    def pending(self) -> list[str]:
        """Return outstanding request ids in the order they were expected."""
        return list(self._deadlines)

    def __len__(self) -> int:
        return len(self._deadlines)

    def __contains__(self, request_id: object) -> bool:
        return request_id in self._deadlines

"""The live feed to dashboards: coalesced metric values and low-rate state events.

A `group_send` per frame caps a consumer at under 1,000 frames/s and overflows subscribers,
so metrics are coalesced per process to the latest value per series and sent to the
`live` group as one message, each robot's payload already JSON-encoded. Points arrive once
their batch commits, so the feed sends right after they arrive (a batch's points together)
rather than on a clock of its own, which would add up to a second wait to every value.
Subscribers filter by the robots they may see.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import math
import time
from collections.abc import Iterable, Sequence
from typing import TYPE_CHECKING, Any

from asgiref.sync import SyncToAsync
from channels.layers import BaseChannelLayer, get_channel_layer
from channels_redis.core import RedisChannelLayer
from django.db import transaction

from bridgeos_agent import protocol
from bridgeos_agent.logonce import LogOnce
from bridgeos_agent.protocol import Event as ProtocolEvent
from bridgeos_cloud.layersync import layer_sync
from bridgeos_cloud.loopowned import loop_object

from . import prometheus

if TYPE_CHECKING:
    from bridgeos_agent.protocol import MetricPoint

    from .models import Event
    from .services import LoggedEvent

logger = logging.getLogger(__name__)

LIVE_GROUP = "live"
# State events per group message when many are published at once (bounded message size).
PUBLISH_CHUNK = 250
# How long points go ungathered after a round found nobody watching: a watcher who comes meanwhile
# waits at most this long for values.
UNWATCHED_RECHECK_S = 1.0
# How long a round of state events gathers before it goes to the live group.
EVENT_SETTLE_S = 0.005

# (skill, component, name) of one series of one robot.
SeriesKey = tuple[str | None, str | None, str]


class LiveFeed:
    """Keep the latest value of every series and push the changes to the live group soon after they arrive."""

    def __init__(self, *, interval: float = 0.1, settle: float = 0.01, layer: BaseChannelLayer | None = None) -> None:
        self.interval = interval  # at most one message per interval
        self.settle = settle  # the frames of one committed batch resume their handlers within this
        self.layer = layer
        self.messages_sent = 0
        self.unwatched_sends = 0  # rounds dropped because no client was in the live group
        self._unwatched_until = -math.inf  # monotonic time: until then, points are not even gathered
        self._latest: dict[str, dict[SeriesKey, MetricPoint]] = {}
        self._task: asyncio.Task[None] | None = None
        self._wake = asyncio.Event()

    def add_metrics(self, robot_id: str, points: Sequence[MetricPoint]) -> None:
        """Remember the newest value of each series among the points."""
        if time.monotonic() < self._unwatched_until:
            return  # nobody watched a moment ago; the first points after that look again
        series = self._latest.get(robot_id)
        if series is None:
            series = self._latest[robot_id] = {}
        for point in points:
            key = (point.get("skill"), point.get("component"), point["name"])
            known = series.get(key)
            # A robot resending its outbox after a reconnect must not replace newer values.
            if known is None or point["ts"] >= known["ts"]:
                series[key] = point
        self.start()
        self._wake.set()

    def start(self) -> None:
        """Start the sender on the running loop, if not yet started."""
        if self._task is None:
            self._task = asyncio.get_running_loop().create_task(self._run(), name="live-feed")

    async def close(self) -> None:
        """Stop the periodic sender after sending what is still pending."""
        if self._task is not None:
            self._task.cancel()
            try:
                await self._task
            except asyncio.CancelledError:
                pass
            self._task = None
        await self.send()

    async def send(self) -> None:
        """Send the values gathered since the last send as one message, if any."""
        if not self._latest:
            return
        latest, self._latest = self._latest, {}
        layer = self.layer or get_channel_layer()
        if layer is None or not await has_members(layer, LIVE_GROUP):
            # Nobody watches, in any process: a watcher who comes gets the values that arrive after.
            # Encoding 10,000 robots' values for nobody was a ninth of daphne's main thread (py-spy).
            self.unwatched_sends += 1
            self._unwatched_until = time.monotonic() + UNWATCHED_RECHECK_S
            return
        # Each robot's payload is encoded once here, not once per subscribed client.
        robots = {robot_id: metrics_data_json(robot_id, series.values()) for robot_id, series in latest.items()}
        await layer.group_send(LIVE_GROUP, {"type": "live.metrics", "robots": robots})
        self.messages_sent += 1
        prometheus.LIVE_MESSAGES.inc()

    async def _run(self) -> None:
        failures = LogOnce(logger, "Sending live metrics", traceback=True)
        loop = asyncio.get_running_loop()
        last_sent = -math.inf
        while True:
            await self._wake.wait()
            await asyncio.sleep(max(self.settle, self.interval - (loop.time() - last_sent)))
            # Cleared before send() takes the values: a point added during the send wakes the next round.
            self._wake.clear()
            last_sent = loop.time()
            try:
                await self.send()
            except Exception as exc:
                # Live values are expendable: the next round carries fresher ones.
                prometheus.LIVE_DROPS.inc()
                failures.failed(exc)
            else:
                failures.worked()


async def has_members(layer: BaseChannelLayer, group: str) -> bool:
    """Tell whether any channel, in any process, is in a group (True where the layer cannot say)."""
    if isinstance(layer, RedisChannelLayer):
        # The group's sorted set, as channels-redis keeps it; a member of a process killed without
        # leaving counts until the layer's group expiry, and costs only the encoding it always did.
        connection = layer.connection(layer.consistent_hash(group))
        return bool(await connection.zcard(layer._group_key(group)))
    groups = getattr(layer, "groups", None)  # the in-memory layer's
    return bool(groups.get(group)) if isinstance(groups, dict) else True


def metrics_data_json(robot_id: str, points: Iterable[MetricPoint]) -> str:
    """Encode the data of a cloud-to-client metrics frame: the robot and its latest points."""
    encoded: list[Any] = []
    for point in points:
        if "labels" not in point and None not in point.values():
            # Already the shape clients get (the protocol's field order, nothing empty): no copy needed.
            encoded.append(point)
            continue
        item: dict[str, Any] = {"name": point["name"], "value": point["value"], "ts": point["ts"]}
        skill, component = point.get("skill"), point.get("component")
        if skill:
            item["skill"] = skill
        if component:
            item["component"] = component
        encoded.append(item)
    return json.dumps({"robot": robot_id, "metrics": encoded}, separators=(",", ":"))


def _started_feed() -> LiveFeed:
    feed = LiveFeed()
    feed.start()
    return feed


def get_live_feed() -> LiveFeed:
    """Return this event loop's live feed, started on first use; its owner closes it at shutdown."""
    return loop_object("live feed", _started_feed)


class EventSender:
    """Send a process's state events to the live group in order, those of a few milliseconds as one message.

    A robot's report publishes its new state and its event-log entry; a group send for each held
    a thousand robots' rollout to the pace of daphne's round trips to Redis. Queued on the loop,
    the database thread that committed goes on at once, and the events of one round go together.
    The sending task lives only while events wait, so an idle loop holds no task of it.
    """

    def __init__(self, *, settle: float = EVENT_SETTLE_S, layer: BaseChannelLayer | None = None) -> None:
        self.settle = settle
        self.layer = layer
        self._queue: list[dict[str, Any]] = []
        self._task: asyncio.Task[None] | None = None
        self._failures = LogOnce(logger, "Sending live events", traceback=True)

    def add(self, messages: list[dict[str, Any]]) -> None:
        """Queue ``live.event`` messages, to be sent after the ones queued before them."""
        self._queue.extend(messages)
        if self._task is None:
            self._task = asyncio.get_running_loop().create_task(self._run(), name="live-events")

    async def close(self) -> None:
        """Send what is still queued."""
        if self._task is not None:
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._task
        await self.send()

    async def send(self) -> None:
        """Send what is queued now."""
        queued, self._queue = self._queue, []
        await group_send_events(self.layer or get_channel_layer(), queued)

    async def _run(self) -> None:
        try:
            while self._queue:
                await asyncio.sleep(self.settle)
                try:
                    await self.send()
                except Exception as exc:
                    # Live events are expendable (a dashboard reads the state again when it reconnects).
                    prometheus.LIVE_DROPS.inc()
                    self._failures.failed(exc)
                else:
                    self._failures.worked()
        finally:
            self._task = None


async def group_send_events(layer: BaseChannelLayer | None, messages: list[dict[str, Any]]) -> None:
    """Send ``live.event`` messages to the live group, a few hundred per group message (one alone as itself)."""
    if layer is None:
        return
    for start in range(0, len(messages), PUBLISH_CHUNK):
        chunk = messages[start : start + PUBLISH_CHUNK]
        await layer.group_send(LIVE_GROUP, chunk[0] if len(chunk) == 1 else {"type": "live.events", "events": chunk})


def get_event_sender() -> EventSender:
    """Return this event loop's sender of state events; its owner closes it at shutdown."""
    return loop_object("live event sender", EventSender)


def event_message(robot_id: str | None, frame: dict[str, Any], organization_id: int | None = None) -> dict[str, Any]:
    """Return the live group's message of one state event (no robot: staff's, or an organization's members' too)."""
    message: dict[str, Any] = {"type": "live.event", "robot": robot_id, "frame": frame}
    if organization_id is not None:
        message["organization"] = organization_id
    return message


async def _send_now(messages: list[dict[str, Any]]) -> None:
    await group_send_events(get_channel_layer(), messages)


def _post(messages: list[dict[str, Any]]) -> None:
    """Hand committed state events to the live group: queued on daphne's loop, or sent before returning elsewhere."""
    loop = getattr(SyncToAsync.threadlocal, "main_event_loop", None)
    if loop is not None and loop.is_running():
        # A consumer's database thread or a sync view: daphne's loop sends them in order, soon.
        loop.call_soon_threadsafe(lambda: get_event_sender().add(messages))
        return
    # A Celery worker or a command (no loop waits on this thread): sent through the kept loop now.
    layer_sync(_send_now)(messages)


def publish_on_commit(robot_id: str, frame: dict[str, Any], *, using: str | None = None) -> None:
    """Publish a state event once the current transaction commits, never if it rolls back."""

    def send() -> None:
        _post([event_message(robot_id, frame)])

    # robust: the change is committed already, so a broadcast failure must not fail the caller. (A named
    # function, not a partial: Django logs a robust callback's failure by its __qualname__.)
    transaction.on_commit(send, using=using, robust=True)


def publish_log_event_on_commit(event: Event, *, organization_id: int | None = None) -> None:
    """Push an event-log entry to the dashboards that may see it, once its transaction commits.

    An entry about a robot that is gone (``robot_deleted``) names it in its data; ``organization_id``
    lets its organization hear of it although the robot no longer says whose it was.
    """
    robot_id, frame = log_event_frame(event)

    def send() -> None:
        _post([event_message(robot_id, frame, organization_id)])

    transaction.on_commit(send, using=event._state.db, robust=True)


def log_event_frame(event: Event | LoggedEvent) -> tuple[str | None, dict[str, Any]]:
    """Return the robot an event-log entry is about and the frame that shows it to dashboards."""
    robot_id = event.robot_id or (event.data or {}).get("robot")
    data = {
        "robot": robot_id,
        "id": event.id,
        "ts": event.ts.isoformat().replace("+00:00", "Z"),
        "level": event.level,
        "source": event.source,
        "kind": event.kind,
        "skill": event.skill,
        "component": event.component,
        "message": event.message[:4000],
        "data": event.data or {},
    }
    return robot_id, protocol.as_json_data(protocol.make(ProtocolEvent.LOG_EVENT, data, now=time.time()))


def publish_all_on_commit(frames: list[tuple[str | None, dict[str, Any]]], *, using: str | None = None) -> None:
    """Publish many (robot, frame) state events once the transaction commits, a few hundred per message."""

    def send() -> None:
        _post([event_message(robot_id, frame) for robot_id, frame in frames])

    if frames:
        transaction.on_commit(send, using=using, robust=True)

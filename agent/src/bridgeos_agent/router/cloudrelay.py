"""Cloud-side routing: a cloud relay delivers what goes from a cloud instance to a cloud instance.

The cloud relay is the same Skill Router code run in the cloud for one robot's Skill
(``python -m bridgeos_agent.router.cloudrelay``, started by the cloud's worker next to the
robot's ROS master). It advertises and subscribes only the *cloud* instances' names and
delivers only the (topic, subscriber) pairs whose publisher and subscriber are both active in
the cloud; the robot's router (through its :class:`CloudLink`) hands those pairs to it,
stops relaying them and stops subscribing to a cloud publisher nobody on the robot needs, so
their bytes no longer cross the robot's link (twice).

Which relay delivers each pair, and how a pair changes hands exactly, is router/handover.py;
the robot's side of the link is router/cloudlink.py. The robot's router keeps the canonical
names (outside nodes live on the robot's graph), the services and the HTTP routes. Statistics:
the relay publishes its own windows on ``/statistics`` and the robot's router adds the relay's
totals (polled) to what it reports to the Skill Manager.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import hmac
import json
import logging
import os
import secrets
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

from aiohttp import web

from bridgeos_agent.rosnames import canonical_name
from bridgeos_agent.router.core import SkillRouter
from bridgeos_agent.router.handover import AWAY, QUIET_S, FrameLog, cloud_pairs, drained, start_after
from bridgeos_agent.router.settings import RouterSettings, Where, locations
from bridgeos_agent.skillconfig import SkillConfig, parse_skill_config

if TYPE_CHECKING:
    pass

__all__ = ["CloudRelay", "main", "serve"]

logger = logging.getLogger(__name__)

REFRESH_S = 2.0  # how often the relay asks the master about sources it has not heard yet


# --------------------------------------------------------------------------- the cloud side


class CloudRelay(SkillRouter):
    """A Skill Router run in the cloud for one robot: it delivers the pairs the robot's router hands it."""

    canonical_names = False

    def __init__(
        self,
        config: SkillConfig,
        *,
        ros_master: str,
        token: str,
        settings: RouterSettings | None = None,
        robot: str | None = None,
    ) -> None:
        super().__init__(config, ros_master=ros_master, settings=settings, robot=robot)
        self.node_name = self.node_name.replace("/router", "/cloudrelay", 1)
        self.token = token
        self.control_url: str | None = None
        self.control_port = 0  # the control API's port (0: any free one)
        self._control: web.AppRunner | None = None

    def _places(self, where: str) -> tuple[Where, ...]:
        return tuple(location for location in locations(where) if location == "cloud")

    def _add_topic(self, route: Any) -> None:
        super()._add_topic(route)
        topic = self._topics[canonical_name(route.name)]
        topic.log = FrameLog()
        for delivery in topic.deliveries.values():
            delivery.gate = AWAY  # nothing is ours until the robot's router hands it over
        topic.parked = True

    def _add_service(self, service: Any) -> None:
        """Leave services to the robot's router (it proxies each call to the active server)."""

    async def start(self) -> None:
        """Route the cloud instances' topics and serve the control API."""
        if self.ros_routes:
            await self.enable_ros(self.ros_master)
        app = web.Application(middlewares=[self._auth])
        app.router.add_post("/take", self._take)
        app.router.add_post("/release", self._release)
        app.router.add_post("/reset", self._reset)
        app.router.add_get("/ready", self._ready_view)
        app.router.add_get("/statistics", self._statistics_view)
        self._spawn(self._refresh_loop())
        self._control = web.AppRunner(app, access_log=None)
        await self._control.setup()
        site = web.TCPSite(self._control, self.settings.http_host, self.control_port)
        await site.start()
        port = site._server.sockets[0].getsockname()[1]  # type: ignore[union-attr]
        self.control_url = f"http://{self.settings.http_advertise}:{port}"

    async def _refresh_loop(self) -> None:
        """Ask the master again for the publishers of every source not connected yet."""
        # The relay sits across the robot's link from the master (the robot's own, usually): a
        # lost publisherUpdate would otherwise leave a cloud source unheard for good.
        while True:
            await asyncio.sleep(REFRESH_S)
            node = self.node
            if node is None:
                continue
            for name, subscription in list(node.subscriptions.items()):
                if subscription.where is not None and not subscription.connected:
                    node.subscribe(name, subscription.type, subscription.callback)

    async def close(self) -> None:
        await super().close()
        if self._control is not None:
            await self._control.cleanup()
            self._control = None

    @web.middleware
    async def _auth(self, request: web.Request, handler: Any) -> web.StreamResponse:
        given = request.headers.get("Authorization", "")
        if not hmac.compare_digest(given.encode(), f"Bearer {self.token}".encode()):
            return web.json_response({"error": "a cloud relay answers only its robot's router"}, status=401)
        return await handler(request)

    async def _body(self, request: web.Request) -> tuple[dict[str, Where | None], list[list[Any]]]:
        """Read and check a handover request: the robot's active map and the pairs; raise 400 on anything wrong."""
        try:
            body = await request.json()
            active = body["active"]
            pairs = body["pairs"]
            if not isinstance(active, dict) or not isinstance(pairs, list):
                raise TypeError("active must be an object and pairs a list")
            for component, location in active.items():
                self._check(component, location)
            for pair in pairs:
                topic = self._topics.get(pair[0])
                if topic is None or pair[1] not in topic.deliveries:
                    raise ValueError(f"no routed pair {pair[0]!r} -> {pair[1]!r}")
        except (ValueError, TypeError, KeyError, IndexError) as exc:
            raise web.HTTPBadRequest(text=json.dumps({"error": str(exc)}), content_type="application/json") from None
        return active, pairs

    def _park(self) -> None:
        """Stop any pair the active map no longer makes cloud to cloud; mark topics with nothing to deliver."""
        pairs = cloud_pairs(self._topics.values(), self._active)
        for topic in self._topics.values():
            for subscriber, delivery in topic.deliveries.items():
                if delivery.gate is not AWAY and (topic.canonical, subscriber) not in pairs:
                    logger.warning("%s -> %s: no longer cloud to cloud; stopped", topic.canonical, subscriber)
                    delivery.gate = AWAY
        for topic in self._topics.values():
            topic.parked = all(d.gate is AWAY for d in topic.deliveries.values())

    async def _take(self, request: web.Request) -> web.Response:
        active, pairs = await self._body(request)
        for pair in pairs:
            if active.get(pair[1]) != "cloud" or active.get(self._topics[pair[0]].route.publisher) != "cloud":
                return web.json_response({"error": f"{pair[0]} -> {pair[1]} is not cloud to cloud"}, status=400)
        self._active = dict(active)
        for name, subscriber, anchor in pairs:
            topic = self._topics[name]
            start_after(topic, topic.deliveries[subscriber], "cloud", anchor, self.settings.drain_timeout)
        self._park()
        return web.json_response({"taken": len(pairs)})

    async def _release(self, request: web.Request) -> web.Response:
        active, pairs = await self._body(request)
        anchors, publications = [], []
        for name, subscriber in pairs:
            topic = self._topics[name]
            delivery = topic.deliveries[subscriber]
            was_ours = delivery.gate is None
            delivery.gate = AWAY
            publications.append(delivery.cloud)
            same_stream = was_ours and active.get(topic.route.publisher) == "cloud" and topic.log is not None
            anchors.append([name, subscriber, topic.log.anchor() if same_stream else None])
        self._active = dict(active)
        self._park()
        await drained(publications, self.settings.drain_timeout)
        await asyncio.sleep(QUIET_S)
        return web.json_response({"anchors": anchors})

    async def _reset(self, request: web.Request) -> web.Response:
        for topic in self._topics.values():
            for delivery in topic.deliveries.values():
                delivery.gate = AWAY
        self._park()
        return web.json_response({"reset": True})

    async def _ready_view(self, request: web.Request) -> web.Response:
        component = request.query.get("component", "")
        try:
            self._check(component, "cloud")
        except ValueError as exc:
            return web.json_response({"error": str(exc)}, status=400)
        return web.json_response({"ready": await self._ready(component, "cloud")})

    async def _statistics_view(self, request: web.Request) -> web.Response:
        counts = {
            name: {
                "messages": topic.messages,
                "bytes_cloud": topic.bytes_cloud,
                "dropped": topic.dropped,
                "deliveries": {
                    sub: [d.messages, d.dropped, d.bytes_robot, d.bytes_cloud] for sub, d in topic.deliveries.items()
                },
            }
            for name, topic in self._topics.items()
        }
        return web.json_response({"counts": counts})


# --------------------------------------------------------------------------- the process


async def serve(args: argparse.Namespace, config: SkillConfig) -> None:
    """Run a cloud relay until stopped; print one JSON line with its control URL first."""
    settings = RouterSettings(http_host=args.host, http_advertise=args.host, ros_host=args.host)
    relay = CloudRelay(config, ros_master=args.master, token=args.token, settings=settings, robot=args.robot)
    relay.control_port = args.port
    await relay.start()
    print(json.dumps({"url": relay.control_url, "node": relay.node_name, "ros": relay.ros_on}), flush=True)
    try:
        await asyncio.Event().wait()
    finally:
        await relay.close()


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description="Run one robot's cloud relay for one Skill.")
    parser.add_argument("--config", required=True, help="the Skill config (JSON file)")
    parser.add_argument("--master", required=True, help="the ROS master the robot's Skill uses")
    parser.add_argument("--host", default="127.0.0.1", help="address to listen on and advertise")
    parser.add_argument("--port", type=int, default=0, help="the control API's port (0: any free one)")
    parser.add_argument("--robot", default=None)
    parser.add_argument("--token", default=os.environ.get("BRIDGEOS_CLOUD_RELAY_TOKEN") or secrets.token_urlsafe(24))
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, stream=sys.stderr, format="%(asctime)s %(name)s %(message)s")
    with contextlib.suppress(KeyboardInterrupt):
        asyncio.run(serve(args, parse_skill_config(json.loads(Path(args.config).read_text()))))


if __name__ == "__main__":
    main()

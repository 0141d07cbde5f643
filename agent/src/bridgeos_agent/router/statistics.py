"""Count what a Skill Router routes: ``/statistics`` windows, totals, and each component's traffic."""

from __future__ import annotations

import asyncio
import math
import time
from typing import Any

from bridgeos_agent.router.routes import RoutedTopic, RouterBase
from bridgeos_agent.tcpros import TopicStatistics, frame
from bridgeos_agent.traffic import ComponentTraffic

__all__ = ["STATISTICS_TOPIC", "RouterStatistics"]

STATISTICS_TOPIC = "/statistics"


class RouterStatistics(RouterBase):
    """Publish rosgraph_msgs/TopicStatistics and report totals and traffic to the Skill Manager."""

    async def _statistics_loop(self) -> None:
        period = self.settings.statistics_period
        while True:
            await asyncio.sleep(period)
            self.publish_statistics()

    def publish_statistics(self) -> int:
        """Close every topic's statistics window; publish the busy ones on /statistics; return how many."""
        now = self.clock()
        wall = time.time()
        publication = self._statistics
        listening = publication is not None and publication.connections
        frames = []
        ros2 = []
        for topic in self._topics.values():
            span = now - topic.w_start
            topic.last_rate = topic.w_messages / span if span > 0 else 0.0
            topic.last_age = topic.w_age_sum / topic.w_age_n if topic.w_age_n else None
            if topic.w_messages and getattr(topic, "msg_class", None) is not None:
                ros2.append(self._window(topic, now, wall))  # a ROS 2 topic (router.ros2)
            elif listening and topic.w_messages:
                frames.append(frame(self._window(topic, now, wall).serialize()))
            topic._reset_window(now)
            topic.w_last = 0.0
        if frames and publication is not None:
            publication.send(b"".join(frames), len(frames))
        self._r2_publish_statistics(ros2)
        return len(frames) + len(ros2)

    def _window(self, topic: RoutedTopic, now: float, wall: float) -> TopicStatistics:
        count, total, squares = topic.w_period_n, topic.w_period_sum, topic.w_period_sq
        mean = total / count if count else 0.0
        ages = (topic.w_age_n, topic.w_age_sum, topic.w_age_sq, topic.w_age_max)
        age_mean = ages[1] / ages[0] if ages[0] else 0.0
        return TopicStatistics(
            topic=topic.canonical,
            node_pub=topic.node_pub or topic.route.publisher,
            node_sub=self.node.name if self.node else "",
            window_start=wall - (now - topic.w_start),
            window_stop=wall,
            delivered_msgs=topic.w_messages,
            dropped_msgs=topic.w_dropped,
            traffic=topic.w_bytes,
            period_mean=mean,
            period_stddev=math.sqrt(max(0.0, squares / count - mean * mean)) if count else 0.0,
            period_max=topic.w_period_max,
            stamp_age_mean=age_mean,
            stamp_age_stddev=math.sqrt(max(0.0, ages[2] / ages[0] - age_mean * age_mean)) if ages[0] else 0.0,
            stamp_age_max=ages[3],
        )

    def statistics(self) -> dict[str, dict[str, Any]]:
        """Return each topic's and service's totals since the router started."""
        result: dict[str, dict[str, Any]] = {}
        for topic in self._topics.values():
            delivered = topic.canonical_delivered + sum(d.messages for d in topic.deliveries.values())
            dropped = topic.dropped + topic.outside_dropped
            sent = topic.messages + topic.outside_messages
            result[topic.canonical] = {
                "kind": "topic",
                "publisher": topic.route.publisher,
                "messages": sent,
                "bytes": topic.bytes_robot + topic.bytes_cloud,
                "delivered": delivered,
                "dropped": dropped,
                "delivery_ratio": delivered / (delivered + dropped) if delivered + dropped else 1.0,
                "rate_hz": round(topic.last_rate, 3),
                "latency_ms": None if topic.last_age is None else round(topic.last_age * 1000, 3),
                "subscribers": {
                    name: {"messages": d.messages, "dropped": d.dropped, "bytes": d.bytes_robot + d.bytes_cloud}
                    for name, d in topic.deliveries.items()
                },
            }
        for service in self._services.values():
            result[service.canonical] = {
                "kind": "service",
                "server": service.route.server,
                "calls": service.calls,
                "bytes": service.bytes,
                "errors": service.errors,
            }
        result.update(self.r2_statistics())
        link = getattr(self, "cloud_link", None)
        if link is not None:
            link.merge(result)  # what the cloud relay delivered
        return result

    def _totals(self, component: str) -> tuple[int, int, int, int]:
        """Return (bytes robot, bytes cloud, messages, dropped) routed to or from a component so far."""
        robot = cloud = messages = dropped = 0
        for topic in self._topics.values():
            if topic.route.publisher == component:
                robot += topic.bytes_robot
                cloud += topic.bytes_cloud
                messages += topic.messages
                dropped += topic.dropped
            delivery = topic.deliveries.get(component)
            if delivery is not None:
                robot += delivery.bytes_robot
                cloud += delivery.bytes_cloud
                messages += delivery.messages + delivery.dropped
                dropped += delivery.dropped
        for service in self._services.values():
            if service.route.server == component:
                robot += service.bytes
                messages += service.calls
                dropped += service.errors
        for service in self._r2_services.values():
            if service.route.server == component:
                robot += service.bytes
                messages += service.calls
                dropped += service.errors
        counts = self._http_counts.get(component)
        if counts is not None:
            messages += counts[0]
            robot += counts[1]
            dropped += counts[2]
        link = getattr(self, "cloud_link", None)
        if link is not None:
            extra = link.totals(self, component)
            robot, cloud, messages, dropped = (
                a + b for a, b in zip((robot, cloud, messages, dropped), extra, strict=True)
            )
        return robot, cloud, messages, dropped

    def routed(self, component: str) -> bool:
        """Tell whether any route of the Skill's config involves a component."""
        router = self.config.router
        return (
            any(t.publisher == component or component in t.subscribers for t in router.topics)
            or any(s.server == component for s in router.services)
            or any(a.server == component for a in router.actions)
            or any(h.component == component for h in router.http)
        )

    def traffic(self, component: str) -> ComponentTraffic:
        """Return what was routed to or from a component since the previous call (the manager's input).

        Raises KeyError for a component no route involves: the router measures nothing of it.
        """
        if not self.routed(component):
            raise KeyError(f"skill {self.skill!r} routes nothing of component {component!r}")
        now = self.clock()
        totals = self._totals(component)
        since, before = self._last_traffic.get(component, (self._started, (0, 0, 0, 0)))
        self._last_traffic[component] = (now, totals)
        robot, cloud, messages, dropped = (a - b for a, b in zip(totals, before, strict=True))
        return ComponentTraffic(
            seconds=max(0.0, now - since),
            bytes_robot=robot,
            bytes_cloud=cloud,
            messages=messages,
            dropped=dropped,
        )

"""Relay a Skill's ROS topics from the publisher's active instance to every subscriber's (the hot path)."""

from __future__ import annotations

import functools
import time

from bridgeos_agent.rosnames import canonical_name, instance_name
from bridgeos_agent.rostopics import Inbound, Outbound, Publication, Subscription, iter_frames
from bridgeos_agent.router.routes import Delivery, RoutedTopic, RouterBase
from bridgeos_agent.router.settings import Where, locations
from bridgeos_agent.skillconfig import TopicRoute
from bridgeos_agent.tcpros import header_stamp

__all__ = ["TopicRouting"]


class TopicRouting(RouterBase):
    """Advertise, subscribe and relay the routed topics, counting what passes."""

    # The robot's router owns the canonical names (outside nodes live on the robot's graph); a
    # cloud relay serves only the cloud instances (cloudrelay.CloudRelay overrides both).
    canonical_names = True

    def _places(self, where: str) -> tuple[Where, ...]:
        """Return the locations whose instances this router advertises and subscribes for a component."""
        return locations(where)

    def _add_topic(self, route: TopicRoute) -> None:
        node = self.node
        assert node is not None
        components = self.config.components
        canonical = canonical_name(route.name)
        canonical_pub = node.advertise(canonical, route.type) if self.canonical_names else None
        topic = RoutedTopic(route, canonical_pub, self.clock())
        self._topics[canonical] = topic
        for subscriber in route.subscribers:
            if subscriber == route.publisher:
                continue  # never route a component's own messages back to it
            delivery = topic.deliveries[subscriber] = Delivery()
            for location in self._places(components[subscriber].location):
                publication = node.advertise(instance_name(route.name, self.skill, subscriber, location), route.type)
                setattr(delivery, location, publication)
                if topic.store is not None:
                    publication.on_connect = functools.partial(self._replay, topic)
        for location in self._places(components[route.publisher].location):
            name = instance_name(route.name, self.skill, route.publisher, location)
            subscription = node.subscribe(name, route.type, self._on_messages)
            subscription.owner, subscription.where = topic, location
        if topic.deliveries and self.canonical_names:
            # Outside publishers on the canonical name reach the subscribers too.
            node.subscribe(canonical, route.type, self._on_messages).owner = topic

    def _publications(self, topic: RoutedTopic) -> list[Publication]:
        found = [topic.canonical_pub] if topic.canonical_pub is not None else []
        for delivery in topic.deliveries.values():
            found += [p for p in (delivery.robot, delivery.cloud) if p is not None]
        return found

    def _remove_topic(self, canonical: str) -> None:
        node = self.node
        topic = self._topics.pop(canonical, None)
        if node is None or topic is None:
            return
        for publication in self._publications(topic):
            node.unadvertise(publication.name)
        for name, subscription in list(node.subscriptions.items()):
            if subscription.owner is topic:
                node.unsubscribe(name)

    def _on_publisher_header(self, subscription: Subscription, inbound: Inbound) -> None:
        topic: RoutedTopic | None = subscription.owner
        header = inbound.header or {}
        md5sum = header.get("md5sum", "*")
        if topic is None or md5sum == "*":
            return
        definition = header.get("message_definition", "")
        type_ = header.get("type", topic.route.type)
        for publication in self._publications(topic):
            publication.md5sum, publication.type, publication.definition = md5sum, type_, definition
        first = next((line.split() for line in definition.splitlines() if line.strip() and line[0] != "#"), [])
        topic.has_header = first[:1] in (["Header"], ["std_msgs/Header"])
        if subscription.where is not None:
            topic.node_pub = header.get("callerid", "")

    def _on_messages(self, subscription: Subscription, blob: bytes, count: int, inbound: Inbound) -> None:
        """Relay a burst of frames from one publisher: the router's hot path."""
        topic: RoutedTopic = subscription.owner
        source = subscription.where
        payload = len(blob) - 4 * count
        dropped = 0
        active = self._active
        if source is None:
            # An outside publisher on the canonical name: to every subscriber's active instance.
            topic.outside_messages += count
            for component, delivery in topic.deliveries.items():
                where = active.get(component)
                if where is None:
                    continue
                lost = getattr(delivery, where).send(blob, count)
                delivery.messages += count - lost
                delivery.dropped += lost
                delivery.bytes_robot += payload  # outside nodes live on the robot's ROS graph
                dropped += lost
            topic.outside_dropped += dropped
        else:
            log = topic.log
            if log is not None and source == "cloud":
                log.add(blob, count)  # a handover's cut point is found in here
            if active.get(topic.route.publisher) != source or topic.parked:
                return  # the inactive instance's traffic goes nowhere
            topic.messages += count
            canonical = topic.canonical_pub
            if canonical is not None and canonical.connections:
                lost = canonical.send(blob, count)
                dropped += lost
                topic.canonical_delivered += count - lost
                topic.bytes_robot += payload
            for component, delivery in topic.deliveries.items():
                where = active.get(component)
                if where is None:
                    continue
                if delivery.gate is not None:
                    dropped += delivery.gate.burst(topic, delivery, where, source, blob, count)
                    continue
                lost = getattr(delivery, where).send(blob, count)
                delivery.messages += count - lost
                delivery.dropped += lost
                dropped += lost
                if where == "robot":
                    topic.bytes_robot += payload
                else:
                    topic.bytes_cloud += payload
                if source == "robot":
                    delivery.bytes_robot += payload
                else:
                    delivery.bytes_cloud += payload
            topic.dropped += dropped
        if topic.store is not None:
            topic.store.extend(iter_frames(blob))
        # The statistics window.
        now = self.clock()
        topic.w_messages += count
        topic.w_bytes += payload
        topic.w_dropped += dropped
        if topic.w_last:
            period = (now - topic.w_last) / count
            topic.w_period_n += count
            topic.w_period_sum += period * count
            topic.w_period_sq += period * period * count
            if period > topic.w_period_max:
                topic.w_period_max = period
        topic.w_last = now
        if topic.has_header:
            stamp = header_stamp(blob, 0)
            if stamp:
                age = time.time() - stamp
                topic.w_age_n += 1
                topic.w_age_sum += age
                topic.w_age_sq += age * age
                if age > topic.w_age_max:
                    topic.w_age_max = age

    def _replay(self, topic: RoutedTopic, connection: Outbound) -> None:
        """Give a newly connected instance the topic's stored messages first."""
        if topic.store:
            connection.send(b"".join(topic.store), len(topic.store))

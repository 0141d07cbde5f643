"""The Skill Router (thesis §3.4.2): hides where each component of a Skill runs.

Every component instance runs in a namespace of its own (``rosnames.instance_namespace``),
so the robot and cloud copies of a component never meet. The router relays each topic of
the Skill's ``router`` section from the publisher's *active* instance to the canonical name
and to every subscriber's active instance (and from outside publishers on the canonical
name to the subscribers), proxies ROS services and HTTP routes to the server's active
instance, and switches an instance active with one flag once the new one is ready. It
forwards message bytes without decoding them, keeps one bounded queue per subscriber
connection so a slow peer or a big topic never delays another, keeps the last N messages
of marked topics for new instances, counts everything for the Skill Manager and publishes
``rosgraph_msgs/TopicStatistics`` on ``/statistics``.

Cloud-side routing (``cloudrelay``): the same router run in the cloud for one robot's Skill, a
cloud relay, delivers the (topic, subscriber) pairs whose two ends are both active in the cloud,
so their bytes do not cross the robot's link. Through its link to the relay (``cloudlink``)
the robot's router hands those pairs over and takes them back at an exact cut point
(``handover``: one relay per pair at any moment, nothing lost or repeated), stops receiving
cloud streams nobody on the robot needs, adds the relay's counts to its own, and relays
everything itself (said once in its log) when no relay answers.
Routes of ROS 2 components (``"ros": 2``) go through rclpy instead (``router.ros2``, imported
only when such a route exists): serialized messages mirroring the publisher's QoS, services,
actions as their hidden services and topics, the robot's graph and the cloud's (a client of
the robot's discovery server, given by ``SkillRouter.set_ros2_graphs``), and per-topic
``diagnostic_msgs/DiagnosticArray`` on the ROS 2 ``/statistics``. Routes that cannot run
(bad types, unmatched QoS) land in ``route_errors`` and ``on_route_error``.
"""

from __future__ import annotations

from bridgeos_agent.router.core import SkillRouter, skill_router_plugin
from bridgeos_agent.router.settings import LOCATIONS, RouterSettings, Where, router_settings_from_env
from bridgeos_agent.router.statistics import STATISTICS_TOPIC

__all__ = [
    "LOCATIONS",
    "STATISTICS_TOPIC",
    "RouterSettings",
    "SkillRouter",
    "Where",
    "router_settings_from_env",
    "skill_router_plugin",
]

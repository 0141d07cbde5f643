"""The router part of a rollout's health gate: the drop share of the rates a robot reported of its Skill Router."""

from __future__ import annotations

from datetime import timedelta

import pytest
from django.contrib.auth import get_user_model
from django.utils import timezone

from bridgeos_agent.delivery import ROUTER_DELIVERED, ROUTER_DROPPED
from monitoring.models import Metric
from robots.services import create_robot
from rollouts.health import router_problem
from rollouts.models import Rollout, RolloutRobot
from rollouts.services import create_release
from teams.services import personal_organization

pytestmark = pytest.mark.django_db

ROUTED = {
    "skill": "Talk",
    "skill_id": "talk",
    "components": {
        name: {"name": name.title(), "location": "robot", "ros": True, "robot": {"command": ["sleep", "600"]}}
        for name in ("talker", "listener")
    },
    "router": {
        "topics": [{"name": "/chatter", "type": "std_msgs/String", "publisher": "talker", "subscribers": ["listener"]}]
    },
}


def verifying(config: dict, gates: dict | None = None) -> RolloutRobot:
    """A robot of a rollout of ``config``, verified since ten seconds ago."""
    owner = get_user_model().objects.create_user("router-owner")
    robot, _ = create_robot("router-bot", owner)
    made = create_release(personal_organization(owner), config, user=owner)
    rollout = Rollout.objects.create(
        organization=made.organization, release=made, selector="a=b", gates=gates or {}, batch_sizes=[1]
    )
    return RolloutRobot.objects.create(
        rollout=rollout, robot=robot, batch=0, status="verifying", verify_from=timezone.now() - timedelta(seconds=10)
    )


def reported(member: RolloutRobot, name: str, *values: float) -> None:
    """Store rates as the robot's metrics frames would, one a second through the soak."""
    start = member.verify_from
    Metric.objects.bulk_create(
        Metric(robot_id=member.robot_id, skill="talk", name=name, value=v, ts=start + timedelta(seconds=1 + i))
        for i, v in enumerate(values)
    )


def test_a_router_dropping_more_than_the_gate_allows_fails_the_robot():
    member = verifying(ROUTED)
    reported(member, ROUTER_DELIVERED, 90, 90, 90)
    reported(member, ROUTER_DROPPED, 10, 10, 10)
    problem = router_problem(member.rollout, member, timezone.now())
    assert problem == "the Skill Router dropped 10.0% of its messages over the soak (the gate allows 5.0%)"


def test_a_router_within_the_gate_or_quiet_passes_and_the_gate_can_allow_more():
    member = verifying(ROUTED, gates={"router_dropped_max": 0.2})
    assert router_problem(member.rollout, member, timezone.now()) == ""  # it routed nothing: nothing dropped
    reported(member, ROUTER_DELIVERED, 90, 90)
    reported(member, ROUTER_DROPPED, 10, 10)
    assert router_problem(member.rollout, member, timezone.now()) == ""
    # Rates from before the soak (the old version's router) do not count.
    Metric.objects.create(
        robot_id=member.robot_id,
        skill="talk",
        name=ROUTER_DROPPED,
        value=1000,
        ts=member.verify_from - timedelta(seconds=1),
    )
    assert router_problem(member.rollout, member, timezone.now()) == ""


def test_a_skill_without_routes_has_no_router_gate():
    unrouted = {key: value for key, value in ROUTED.items() if key != "router"}
    member = verifying(unrouted)
    reported(member, ROUTER_DROPPED, 50)
    assert router_problem(member.rollout, member, timezone.now()) == ""

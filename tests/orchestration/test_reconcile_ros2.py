"""The reconciler adopts a ROS 2 cloud copy that runs while its row says it starts (process runtime, no mocks)."""

from __future__ import annotations

import pytest
from django.contrib.auth import get_user_model

from bridgeos_agent.skillconfig import parse_skill_config
from robots.services import create_robot
from skills.cloud.converge import run_copy, stop_copy
from skills.cloud.reconcile import reconcile
from skills.models import CloudInstance, Component
from skills.services import add_skill

pytestmark = [pytest.mark.django_db(transaction=True), pytest.mark.timeout(120)]


def test_a_running_ros2_copy_whose_row_says_starting_is_recorded_running(settings):
    settings.BRIDGEOS = {**settings.BRIDGEOS, "CLOUD_RUNTIME": "process"}
    owner = get_user_model().objects.create_user("ros2-owner")
    robot, _ = create_robot("ros2-bot", owner)
    robot.ros2 = {"domain_id": 7, "rmw": "rmw_fastrtps_cpp"}
    robot.save(update_fields=["ros2"])
    # A ROS 2 component: its launch spec reads the robot's graph (and discovery server) from the database.
    node = {"name": "Node", "location": "cloud", "ros": 2, "cloud": {"command": ["sh", "-c", "sleep 60", "node"]}}
    add_skill(robot, parse_skill_config({"skill": "R2", "skill_id": "r2", "components": {"node": node}}).model_dump())
    component = Component.objects.get(skill__robot=robot)
    component.active_location = "cloud"
    component.save(update_fields=["active_location"])
    instance = CloudInstance.objects.create(component=component, desired="running", status="pending", runtime="process")
    try:
        assert run_copy(instance) == "running"
        # The worker that launched it died before recording it (or the row was written back): it runs all the same.
        CloudInstance.objects.filter(pk=instance.pk).update(status="starting")

        done = reconcile()

        assert done["restarted"] == 1, done
        instance.refresh_from_db()
        assert instance.status == "running"
        assert Component.objects.get(pk=component.pk).status == "running"
    finally:
        instance.refresh_from_db()
        stop_copy(instance)

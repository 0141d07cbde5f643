"""A robot's ROS 2 graph on the dashboard's robot page: shown to its owner and staff, to no one else."""

from __future__ import annotations

import pytest
from django.contrib.auth import get_user_model

from robots.models import Robot
from robots.services import create_robot

pytestmark = pytest.mark.django_db

GRAPH = {
    "domain_id": 45,
    "rmw": "rmw_fastrtps_cpp",
    "discovery_range": "SUBNET",
    "static_peers": ["10.0.0.7"],
    "discovery_server": None,
    "cloud_discovery_server": "127.0.0.1:42811",
}


@pytest.fixture
def robot():
    owner = get_user_model().objects.create_user("owner", password="owner-pass-123")
    robot, _ = create_robot("r2-page", owner)
    Robot.objects.filter(id=robot.id).update(ros2=GRAPH)
    return robot


def test_the_owner_sees_the_robots_ros2_graph_on_its_page(client, robot):
    client.force_login(robot.owner)
    page = client.get("/robots/r2-page/")
    assert page.status_code == 200
    text = page.content.decode()
    assert 'id="robot-ros2"' in text
    for shown in ("<code>45</code>", "<code>rmw_fastrtps_cpp</code>", "<code>SUBNET</code>", "10.0.0.7"):
        assert shown in text
    assert '<code id="robot-ros2-cloud">127.0.0.1:42811</code>' in text


def test_staff_see_it_and_other_users_do_not_see_the_robot(client, robot):
    staff = get_user_model().objects.create_user("staff", is_staff=True)
    client.force_login(staff)
    assert "127.0.0.1:42811" in client.get("/robots/r2-page/").content.decode()
    client.force_login(get_user_model().objects.create_user("stranger"))
    assert client.get("/robots/r2-page/").status_code == 404


def test_a_robot_without_ros2_shows_no_graph(client, robot):
    Robot.objects.filter(id=robot.id).update(ros2=None)
    client.force_login(robot.owner)
    assert 'id="robot-ros2"' not in client.get("/robots/r2-page/").content.decode()

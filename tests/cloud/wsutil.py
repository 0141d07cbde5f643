"""Helpers for WebSocket tests: robots and clients over real sockets against daphne."""

from __future__ import annotations

from typing import Any

from asgiref.sync import sync_to_async
from django.contrib.auth import get_user_model

from bridgeos_agent.link import Link
from bridgeos_agent.protocol import Event
from bridgeos_agent.skillconfig import load_sample_skill_config
from robots.services import create_robot, issue_api_token
from skills.services import add_skill


@sync_to_async
def make_owner(username: str, *, staff: bool = False):
    """Create a user with an API token; return (user, token key)."""
    user = get_user_model().objects.create_user(username, password=f"{username}-pass-123", is_staff=staff)
    return user, issue_api_token(user)[0]


@sync_to_async
def make_robot(robot_id: str, owner, *, with_skill: bool = True) -> str:
    """Create a robot (with the sample people-detection skill) and return its token."""
    robot, token = create_robot(robot_id, owner)
    if with_skill:
        add_skill(robot, load_sample_skill_config().model_dump(mode="json"))
    return token


async def robot_login(server, robot_id: str, token: str, **credentials: Any) -> tuple[Link, dict]:
    """Connect a robot (with extra credentials: a ROS master, a ROS 2 graph); return the link and the success data."""
    link = Link(server.ws_url + "/ws/robot/")
    success = await link.connect(Event.AUTHENTICATION_ROBOT, {"robot": robot_id, "token": token, **credentials})
    await link.next(Event.CONNECTION_ESTABLISHED)
    await link.next(Event.ROBOT_CONFIG)
    return link, dict(success.data)


async def robot_link(server, robot_id: str, token: str) -> Link:
    """Connect a robot and consume the frames the cloud sends on connect."""
    return (await robot_login(server, robot_id, token))[0]


async def client_link(server, token: str) -> Link:
    """Connect a dashboard or app client with an API token."""
    link = Link(server.ws_url + "/ws/client/")
    await link.connect(Event.AUTHENTICATION_CLIENT, {"token": token})
    return link


async def new_robot_link(server, robot_id: str, owner: str = "owner", *, with_skill: bool = True) -> tuple[Link, str]:
    """Create a user and a robot of theirs, and connect the robot; return its link and the user's API token."""
    user, api_token = await make_owner(owner)
    return await robot_link(server, robot_id, await make_robot(robot_id, user, with_skill=with_skill)), api_token

"""Robot tokens rotated: at once for a leaked one, or with an overlap while a fleet is re-keyed over its connections."""

from __future__ import annotations

import time
from collections.abc import Iterable
from dataclasses import dataclass
from datetime import timedelta

from channels.layers import get_channel_layer
from django.db import transaction
from django.utils import timezone

from bridgeos_agent import protocol
from bridgeos_agent.protocol import Event
from bridgeos_cloud.layersync import layer_sync
from monitoring.services import record_event

from .models import Robot
from .signals import credentials_rotated


def rotate_token(robot: Robot, *, grace_s: float = 0) -> str:
    """Give a robot a new token that works at once; the old one works ``grace_s`` seconds more.

    Without a grace the old token, and any connection made with it, end now (a leaked token);
    with one, a connected robot stays connected and is given the new token over its connection
    (``robot_rekey``); a robot offline meanwhile needs it handed over before the grace ends.
    """
    return _rotate(robot, grace_s)[0]


@dataclass(frozen=True)
class Rotated:
    """A robot whose token was rotated: its new token, and whether it was sent to the robot's live connection."""

    robot: Robot
    token: str
    sent_live: bool


def rotate_tokens(robots: Iterable[Robot], *, grace_s: float) -> list[Rotated]:
    """Rotate the tokens of a fleet with a grace, each robot in its own transaction (see ``rotate_token``)."""
    return [Rotated(robot, *_rotate(robot, grace_s)) for robot in robots]


def _rotate(robot: Robot, grace_s: float) -> tuple[str, bool]:
    """Rotate a robot's token; return it and whether it goes to the robot's live connection."""
    grace_until = timezone.now() + timedelta(seconds=grace_s) if grace_s > 0 else None
    token = robot.issue_token(grace_until=grace_until)
    with transaction.atomic():
        channel = Robot.objects.select_for_update().values_list("channel", flat=True).get(id=robot.id)
        robot.save(update_fields=["token_hash", "previous_token_hash", "previous_token_until"])
        if grace_until is None:
            message = f"Token of robot {robot.id} rotated"
        else:
            message = f"Token of robot {robot.id} rotated; the old one works until {grace_until:%Y-%m-%d %H:%M:%S} UTC"
        record_event(
            message,
            robot_id=robot.id,
            kind="robot_token_rotated",
            data={"grace_s": grace_s, "sent_live": bool(channel and grace_until)},
        )
        if grace_until is None:
            credentials_rotated.send(sender=Robot, robot=robot)
            revoke_on_commit(channel)
        else:
            _rekey_on_commit(channel, token)
    return token, bool(channel and grace_until)


def revoke_on_commit(channel: str) -> None:
    """Close a robot's live connection once the change that revoked its credentials commits."""
    if channel:
        send = layer_sync(get_channel_layer().send)
        transaction.on_commit(lambda: send(channel, {"type": "robot.revoked"}), robust=True)


def _rekey_on_commit(channel: str, token: str) -> None:
    """Give a robot's live connection its new token once the rotation commits (resent until the robot acks)."""
    if channel:
        send = layer_sync(get_channel_layer().send)
        frame = protocol.encode(protocol.make(Event.ROBOT_REKEY, {"token": token}, now=time.time()))
        transaction.on_commit(lambda: send(channel, {"type": "robot.rekey", "frame": frame}), robust=True)


def record_rekeyed(robot_id: str) -> None:
    """Log that a robot acknowledged its new token: it logs in with it from now on."""
    with transaction.atomic():
        record_event(
            f"Robot {robot_id} took its new token over its connection", robot_id=robot_id, kind="robot_rekeyed"
        )

"""The world the hostile scenario plays in: Alice, Bob, Carol and their robots, and sockets that record."""

from __future__ import annotations

import json
import random
import re
import threading
import time
from dataclasses import dataclass

NAME = "hostile"
SKILL = "people-detection"
# The cloud remembers a robot's applied frame ids across connections (and runs): valid frames carry this tag.
RUN = f"{random.getrandbits(40):010x}"


# Members of Alice's organization beside her, with their roles: Vera may only read alice-bot, Otto also command it.
ALICE_MEMBERS = {"vera": "viewer", "otto": "operator"}


@dataclass
class World:
    """Alice owns alice-bot, Bob bob-bot, Carol carol-bot (each with the sample Skill); ops is staff.

    Vera (viewer) and Otto (operator) are members of Alice's organization, where alice-bot is.
    """

    http: str
    ws: str
    tokens: dict[str, str]  # alice, bob, ops, carol, vera, otto -> API token
    robot_tokens: dict[str, str]  # robot id -> robot token
    sessions: dict[str, str]  # alice, bob, vera -> session key
    template_id: int
    copy_tokens: dict[str, str]  # robot id -> launch token of its cloud copy of the sampler
    recording_id: str  # a finished recording of alice-bot's


def make_world(http: str, ws: str) -> World:
    """Create the users, robots, cloud copies and sessions the scenario plays with."""
    import importlib
    from datetime import timedelta

    from django.conf import settings
    from django.contrib.auth import BACKEND_SESSION_KEY, HASH_SESSION_KEY, SESSION_KEY, get_user_model
    from django.db import connection
    from django.utils import timezone

    from bridgeos_agent.skillconfig import load_sample_skill_config
    from monitoring.models import Metric
    from robots.models import Robot
    from robots.services import create_robot, issue_api_token
    from skills.models import CloudInstance, Component
    from skills.services import add_skill, create_template
    from teams.models import Membership
    from teams.services import personal_organization

    Robot.objects.filter(id__in=["alice-bot", "bob-bot", "carol-bot"]).delete()
    users, tokens, robot_tokens, sessions, copy_tokens = {}, {}, {}, {}, {}
    for name in ("alice", "bob", "ops", "carol", *ALICE_MEMBERS):
        get_user_model().objects.filter(username=f"hostile-{name}").delete()
        users[name] = get_user_model().objects.create_user(f"hostile-{name}", is_staff=name == "ops")
        tokens[name] = issue_api_token(users[name])[0]
    config = load_sample_skill_config().model_dump(mode="json")
    for owner in ("alice", "bob", "carol"):
        robot, robot_tokens[f"{owner}-bot"] = create_robot(f"{owner}-bot", users[owner])
        add_skill(robot, config)
    for name, role in ALICE_MEMBERS.items():
        Membership.objects.create(organization=personal_organization(users["alice"]), user=users[name], role=role)
    store = importlib.import_module(settings.SESSION_ENGINE).SessionStore
    for name in ("alice", "bob", "vera"):
        session = store()
        session[SESSION_KEY] = str(users[name].pk)
        session[BACKEND_SESSION_KEY] = "django.contrib.auth.backends.ModelBackend"
        session[HASH_SESSION_KEY] = users[name].get_session_auth_hash()
        session.create()
        sessions[name] = session.session_key
    for robot_id in ("alice-bot", "bob-bot"):
        component = Component.objects.get(skill__robot_id=robot_id, skill__skill_id=SKILL, component_id="sampler")
        copy_tokens[robot_id] = f"copy{robot_id.replace('-', '')}{random.randrange(10**9)}"
        CloudInstance.objects.update_or_create(
            component=component, defaults={"desired": CloudInstance.Desired.RUNNING, "token": copy_tokens[robot_id]}
        )
    a_minute_ago = timezone.now() - timedelta(minutes=1)
    Metric.objects.bulk_create(
        Metric(robot_id=robot_id, name="cpu", value=0.5, ts=a_minute_ago) for robot_id in ("alice-bot", "bob-bot")
    )
    template_config = {**config, "skill_id": "hostile-counting", "skill": "Hostile counting"}
    from skills.models import SkillTemplate

    SkillTemplate.objects.filter(name="Hostile counting").delete()
    template = create_template(name="Hostile counting", config=template_config)
    from recordings.choices import RecordingStatus
    from recordings.models import Recording

    recording = Recording.objects.create(
        robot_id="alice-bot", topics=["/chatter"], status=RecordingStatus.FINISHED, max_bytes=1, max_duration_s=1
    )
    connection.close()
    return World(http, ws, tokens, robot_tokens, sessions, template.pk, copy_tokens, recording.id.hex)


def daphne_errors(log_text: str) -> int:
    """Count what daphne's log says went wrong on the server: tracebacks and 5xx answers."""
    tracebacks = log_text.count("Traceback (most recent call last)")
    answers_5xx = len(re.findall(r'" 5\d\d ', log_text))
    return tracebacks + answers_5xx


class RecordingRobot:
    """A robot on /ws/robot/ that acks what needs it and records every other frame the cloud sends it."""

    def __init__(self, ws_url: str, robot_id: str, token: str) -> None:
        from websockets.sync.client import connect

        from bridgeos_agent import protocol

        self.protocol = protocol
        self.ws = connect(ws_url + "/ws/robot/", max_size=2**22)
        self.ws.send(
            json.dumps({"event": "authentication_robot", "id": "auth", "data": {"robot": robot_id, "token": token}})
        )
        first = json.loads(self.ws.recv(timeout=10))
        if first["event"] != "authentication_success":
            raise RuntimeError(f"{robot_id} could not authenticate: {first}")
        self.frames: list[dict] = []
        self.lock = threading.Lock()
        self.reader = threading.Thread(target=self.read, daemon=True)
        self.reader.start()

    def read(self) -> None:
        from websockets.exceptions import ConnectionClosed

        try:
            for raw in self.ws:
                frame = json.loads(raw)
                if frame["event"] in self.protocol.REQUIRES_ACK:
                    self.ws.send(self.protocol.encode(self.protocol.ack_frame(frame["id"], now=time.time())))
                with self.lock:
                    self.frames.append(frame)
        except ConnectionClosed:
            pass

    def commands_since(self, index: int) -> list[dict]:
        """Return the frames received since ``index`` that carry an order or a request to the robot."""
        with self.lock:
            got = self.frames[index:]
        # On connecting the cloud sends the robot its own config and connection; nothing else comes unasked.
        return [f for f in got if f["event"] not in ("connection_established", "robot_config", "ack")]

    def count(self) -> int:
        with self.lock:
            return len(self.frames)

    def close(self) -> None:
        self.ws.close()
        self.reader.join(timeout=5)


class Listener:
    """A client on /ws/client/ that keeps every frame its live feed brings, read on a thread of its own."""

    def __init__(self, ws_url: str, token: str) -> None:
        from websockets.sync.client import connect

        self.ws = connect(ws_url + "/ws/client/", max_size=2**22)
        self.ws.send(json.dumps({"event": "authentication_client", "id": "auth", "data": {"token": token}}))
        answer = json.loads(self.ws.recv(timeout=10))
        if answer["event"] != "authentication_success":
            raise RuntimeError(f"the client could not authenticate: {answer}")
        self.frames: list[str] = []
        self.reader = threading.Thread(target=self.read, daemon=True)
        self.reader.start()

    def read(self) -> None:
        from websockets.exceptions import ConnectionClosed

        try:
            for raw in self.ws:
                self.frames.append(raw if isinstance(raw, str) else raw.decode(errors="replace"))
        except ConnectionClosed:
            pass

    def close(self) -> None:
        self.ws.close()
        self.reader.join(timeout=5)

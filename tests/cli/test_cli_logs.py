"""`bridgeos logs` against a live cloud: lines a robot ships through /ws/robot/, queried and followed."""

from __future__ import annotations

import json
import time
from collections.abc import Iterator

import pytest
from django.contrib.auth import get_user_model

from bridgeos_agent.protocol import Event
from bridgeos_agent.skillconfig import load_sample_skill_config
from robots.services import create_robot, issue_api_token
from skills.services import add_skill
from tests.cli.conftest import lines_of, next_line, stop
from tests.cloud.wsutil import robot_link
from tests.conftest import LoopThread

pytestmark = [pytest.mark.slow, pytest.mark.django_db(transaction=True)]

ROBOT = "cli-logs-r"
SKILL = "people-detection"
LEVELS = ["info", "warning", "error", None]


class Robot:
    """A robot's link to the cloud on a loop of its own, shipping component lines as the agent does."""

    def __init__(self, server, token: str) -> None:
        self.loop = LoopThread()
        self.link = self.loop.run(robot_link(server, ROBOT, token))
        self.seq = 0

    def ship(self, *texts: str, component: str = "detector", levels: list | None = None) -> None:
        """Send lines of a component and wait until the cloud acknowledged (stored) them."""
        now = time.time()
        lines = []
        for index, text in enumerate(texts):
            self.seq += 1
            level = (levels or ["info"])[index % len(levels or ["info"])]
            lines.append({"seq": self.seq, "ts": now + index / 1e6, "stream": "stdout", "level": level, "text": text})

        async def send() -> None:
            frame = await self.link.send(
                Event.COMPONENT_LOGS, {"skill": SKILL, "component": component, "lines": lines, "dropped": 0}
            )
            await self.link.wait_acked(frame)

        self.loop.run(send())

    def close(self) -> None:
        self.loop.run(self.link.close())
        self.loop.stop()


@pytest.fixture
def robot(daphne_server, cli) -> Iterator[Robot]:
    """A connected robot with the people-detection Skill; the CLI acts for its owner through the environment."""
    owner = get_user_model().objects.create_user("cli-logs-owner", password="cli-logs-pass-123")
    other = get_user_model().objects.create_user("cli-logs-other", password="cli-logs-pass-123")
    create_robot("cli-logs-foreign", other)
    made, token = create_robot(ROBOT, owner)
    add_skill(made, load_sample_skill_config().model_dump(mode="json"))
    cli.env.update(BRIDGEOS_URL=daphne_server.url, BRIDGEOS_TOKEN=issue_api_token(owner)[0])
    shipping = Robot(daphne_server, token)
    yield shipping
    shipping.close()


def test_logs_are_queried_by_component_level_text_time_and_pages(cli, robot):
    robot.ship("starting up", "disk almost full", "Traceback: boom", "no level here", levels=LEVELS)
    robot.ship("sampler ready", component="sampler")

    everything = cli("logs", ROBOT, "--json")
    assert everything.code == 0, everything
    assert [line["text"] for line in everything.json()] == [
        "starting up",
        "disk almost full",
        "Traceback: boom",
        "no level here",
        "sampler ready",
    ]
    last = cli("logs", f"{ROBOT}/{SKILL}/detector", "-n", "1")
    assert last.code == 0 and last.out.count("\n") == 1, last
    assert last.out.rstrip().endswith("robot stdout - people-detection/detector: no level here"), last
    texts = lambda *args: [line["text"] for line in cli("logs", ROBOT, "--json", *args).json()]  # noqa: E731
    assert texts("--level", "warning") == ["disk almost full", "Traceback: boom"]
    assert texts("-g", "DISK") == ["disk almost full"]
    assert texts("-g", "bo+m$", "-E") == ["Traceback: boom"]
    assert texts("--since", "1h", "-g", "ready") == ["sampler ready"]
    assert texts("--until", "1h") == []

    bad = cli("logs", ROBOT, "-g", "(", "-E")
    assert bad.code == 1 and bad.err.startswith("Error: q: "), bad
    for hidden in ("nobody", "cli-logs-foreign"):
        for follow in ([], ["-f"]):
            missing = cli("logs", *follow, hidden)
            assert missing.code == 4 and "Error:" in missing.err, missing

    # More lines than one page of the API: the command follows its cursors.
    robot.ship(*(f"flood {n}" for n in range(1, 1301)))
    tail = cli("logs", ROBOT, "-n", "1200", "--json").json()
    assert [line["text"] for line in tail] == [f"flood {n}" for n in range(101, 1301)]
    assert len(cli("logs", ROBOT, "--since", "1h").out.splitlines()) == 1305


def test_logs_follow_prints_the_tail_then_each_new_line(cli, robot):
    robot.ship("before 1", "before 2", "before 3")
    follow = cli.popen("logs", "-f", f"{ROBOT}/{SKILL}", "-n", "2")
    try:
        received = lines_of(follow)
        assert next_line(received, follow, lambda _: True).rstrip().endswith("detector: before 2")
        assert next_line(received, follow, lambda _: True).rstrip().endswith("detector: before 3")
        started = time.monotonic()
        robot.ship("printed just now")
        assert next_line(received, follow, lambda _: True).rstrip().endswith("detector: printed just now")
        assert time.monotonic() - started < 5
    finally:
        stop(follow)

    filtered = cli.popen("logs", "-f", ROBOT, "-n", "0", "--level", "error", "--json")
    try:
        received = lines_of(filtered)
        robot.ship("quiet", "loud", levels=["info", "error"])
        line = json.loads(next_line(received, filtered, lambda _: True))
        assert (line["robot"], line["component"], line["text"], line["level"]) == (ROBOT, "detector", "loud", "error")
    finally:
        stop(filtered)
    assert received.empty()

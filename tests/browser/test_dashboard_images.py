"""The robot page shows a component's image on its way to the robot, then the digest it runs."""

from __future__ import annotations

import pytest

from robots.models import Robot
from skills.services import add_skill

from .conftest import make_robot, make_user, start_skill

pytestmark = [pytest.mark.browser, pytest.mark.django_db(transaction=True)]

expect = pytest.importorskip("playwright.sync_api").expect

DIGEST = "sha256:" + "ab12" * 16
IMAGE = f"registry.example:5000/alice/hello:1@{DIGEST}"


def test_the_robot_page_shows_a_pull_as_it_goes_and_the_pinned_digest_once_the_component_runs(
    browser, simulated_robots, daphne_server
):
    alice = make_user("alice")
    token = make_robot(alice, "alice-bot", sample=None)
    hello = {"name": "Hello", "location": "robot", "robot": {"image": IMAGE, "command": ["/bin/sleep", "600"]}}
    add_skill(
        Robot.objects.get(id="alice-bot"), {"skill": "Hello", "skill_id": "hello", "components": {"hello": hello}}
    )
    simulated_robots.start("alice-bot", token)
    browser.login("alice")
    page = browser.visit("/robots/alice-bot/")
    browser.wait_live()
    row = page.locator('tr[data-component="hello/hello"]')
    expect(row.locator("progress")).to_be_hidden()
    start_skill(daphne_server.url, alice, "alice-bot", "hello")
    # The simulated robot reports a 50 MB pull in quarters, a second apart, as the agent does.
    progress = row.locator("progress")
    expect(progress).to_be_visible(timeout=10_000)
    expect(progress).to_have_attribute("title", f"pulling {IMAGE}: 25.0 of 50.0 MB", timeout=10_000)
    expect(row.locator(".badge.status-running")).to_be_visible(timeout=15_000)
    expect(progress).to_be_hidden()
    image = row.locator(".image")
    expect(image).to_have_text(f"registry.example:5000/alice/hello:1@{DIGEST[:19]}…")
    expect(image).to_have_attribute("title", IMAGE)
    assert browser.console_errors() == []

"""The robot page's button for the robot's rosbridge and Foxglove URLs, in a real Chromium."""

from __future__ import annotations

import re

import pytest
from websockets.exceptions import InvalidStatus
from websockets.sync.client import connect

from robots.models import BridgeTicket

from .conftest import make_robot, make_user

pytestmark = [pytest.mark.browser, pytest.mark.django_db(transaction=True)]
expect = pytest.importorskip(
    "playwright.sync_api", reason="playwright is not installed: pip install -e '.[test]'"
).expect


def test_the_robot_page_gives_ticketed_rosbridge_and_foxglove_urls(browser):
    alice = make_user("alice")
    make_robot(alice, "alice-bot", sample=None)
    browser.login("alice")
    page = browser.visit("/robots/alice-bot/")
    page.get_by_role("button", name="Get rosbridge and Foxglove URLs").click()
    ws_base = browser.base_url.replace("http", "ws", 1)
    rosbridge = page.get_by_label("rosbridge URL")
    expect(rosbridge).to_have_value(re.compile(rf"^{re.escape(ws_base)}/ws/rosbridge/alice-bot/\?ticket=bbt_"))
    expect(page.get_by_label("Foxglove URL")).to_have_value(re.compile(r"/ws/foxglove/alice-bot/\?ticket=bbt_"))
    expect(page.get_by_text("Valid once, until")).to_be_visible()
    browser.screenshot("robot-bridge-urls")
    assert BridgeTicket.objects.filter(robot_id="alice-bot", user=alice).count() == 1

    # The URL works once: the robot is offline, which it says in rosbridge's own words.
    with connect(rosbridge.input_value(), open_timeout=10) as websocket:
        assert "alice-bot is offline" in websocket.recv(timeout=10)
    with pytest.raises(InvalidStatus):
        connect(rosbridge.input_value(), open_timeout=10)

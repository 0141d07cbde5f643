"""The robot page's live topics: a real agent on a real ROS 1 graph, read through the cloud in a real Chromium."""

from __future__ import annotations

import re

import pytest

from .conftest import make_robot, make_user

pytestmark = [pytest.mark.browser, pytest.mark.ros, pytest.mark.django_db(transaction=True), pytest.mark.timeout(120)]
expect = pytest.importorskip(
    "playwright.sync_api", reason="playwright is not installed: pip install -e '.[test]'"
).expect


def test_the_owner_sees_the_robots_live_topics_types_and_a_measured_rate(browser, agents, ros_graph):
    alice = make_user("alice")
    token = make_robot(alice, "alice-bot", sample=None)
    agents.start("alice-bot", token)
    browser.login("alice")
    page = browser.visit("/robots/alice-bot/")
    table = page.locator("#topics")
    load = page.get_by_role("button", name="Show live topics")
    row = table.locator('tr[data-topic="/chatter"]')
    # The talker registers with the master a moment after it starts: ask again until it is listed.
    for _ in range(20):
        load.click()
        expect(page.locator("#topics-result")).to_contain_text("topic")
        if row.count():
            break
        page.wait_for_timeout(250)
    expect(row.locator("td").nth(1)).to_have_text("std_msgs/String")
    expect(table.locator('tr[data-topic="/rosout"]')).to_have_count(1)
    assert "std_msgs/String" in row.inner_text()
    # No topic is subscribed on the robot until a rate is asked for.
    rate = row.locator("td").nth(2)
    expect(rate).to_have_text("—")
    row.get_by_role("button", name="Measure the rate of /chatter").click()
    expect(rate).to_have_text(re.compile(r"msg/s$"), timeout=15_000)
    measured = float(rate.inner_text().split()[0])
    assert 12 <= measured <= 26, measured  # the talker publishes at 20 Hz
    browser.screenshot("robot-live-topics")


def test_another_user_sees_neither_the_robot_page_nor_its_topics(browser):
    alice = make_user("alice")
    make_robot(alice, "alice-bot", sample=None)
    make_user("bob")
    browser.login("bob")
    browser.expect_http_error(404)
    response = browser.page.goto(browser.base_url + "/robots/alice-bot/")
    assert response is not None and response.status == 404
    assert browser.page.locator("#topics-load").count() == 0
    # Nor can bob's session get the ticket the topics are read with.
    answer = browser.page.evaluate(
        """async () => {
            const csrf = document.cookie.match(/csrftoken=([^;]+)/)?.[1] ?? "";
            const r = await fetch("/api/robot/alice-bot/bridge-ticket", {method: "POST", headers: {"X-CSRFToken": csrf}});
            return r.status;
        }"""
    )
    assert answer == 404

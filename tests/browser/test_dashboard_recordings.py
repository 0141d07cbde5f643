"""The robot page's recordings: started, stopped, downloaded and deleted in a real Chromium, from a real agent."""

from __future__ import annotations

import io
import re
from pathlib import Path

import pytest
from mcap.reader import make_reader

from recordings.models import Recording

from .conftest import make_robot, make_user, wait_until

pytestmark = [pytest.mark.browser, pytest.mark.django_db(transaction=True), pytest.mark.timeout(180)]
expect = pytest.importorskip(
    "playwright.sync_api", reason="playwright is not installed: pip install -e '.[test]'"
).expect


# The form's fields by their labels (an error shown under a field becomes part of its label's text).
FIELDS = {
    "Topics": ("textbox", "Topics (comma or space separated)"),
    "ROS": ("combobox", "ROS"),
    "Max size (MiB)": ("spinbutton", "Max size (MiB)"),
    "Max duration (s)": ("spinbutton", "Max duration (s)"),
}


def field(page, label: str):
    role, name = FIELDS[label]
    return page.locator("#recording-form").get_by_role(role, name=re.compile("^" + re.escape(name)))


def start(page, topics: str, *, mib: str = "", seconds: str = "", ros: str = "auto") -> None:
    """Fill the recording form as an operator does and submit it."""
    field(page, "Topics").fill(topics)
    field(page, "ROS").select_option(label=ros)
    field(page, "Max size (MiB)").fill(mib)
    field(page, "Max duration (s)").fill(seconds)
    page.locator("#recording-form").get_by_role("button", name="Start recording").click()


def error_shown(page, field_label: str | None, says: str) -> None:
    """Check the API's refusal is shown in the form's summary and, when it names a field, under that field."""
    expect(page.locator("#recording-form .error-summary")).to_contain_text(says)
    if field_label is not None:
        box = field(page, field_label)
        expect(box).to_have_attribute("aria-invalid", "true")
        expect(page.locator(f"#{box.get_attribute('aria-describedby')}")).to_contain_text(says)


@pytest.mark.ros
def test_the_owner_records_chatter_from_the_page_then_stops_downloads_and_deletes_it(browser, agents, ros_graph):
    alice = make_user("alice")
    token = make_robot(alice, "alice-bot", sample=None)
    agents.start("alice-bot", token)
    browser.login("alice")
    page = browser.visit("/robots/alice-bot/")
    expect(page.locator("#recordings-empty")).to_be_visible()

    # Once the Live topics card has listed the robot's topics, the form offers them.
    topics = field(page, "Topics")
    offer = page.get_by_role("button", name="Add /chatter to the recording")
    for _ in range(20):  # the talker registers with the master a moment after it starts
        page.get_by_role("button", name="Show live topics").click()
        expect(page.locator("#topics-result")).to_contain_text("topic")
        if offer.count():
            break
        page.wait_for_timeout(250)
    offer.click()
    expect(topics).to_have_value("/chatter")

    # A topic the robot does not have: the robot's refusal, under the field; nothing recorded, input kept.
    browser.expect_http_error(400)
    start(page, "/chatter, /no_such_topic")
    error_shown(page, "Topics", "/no_such_topic")
    expect(topics).to_have_value("/chatter, /no_such_topic")
    assert Recording.objects.count() == 0

    start(page, "/chatter", seconds="120")
    row = page.locator("#recordings tbody tr")
    expect(row).to_have_count(1)
    expect(page.locator("#recording-form .error-summary")).to_have_count(0)
    status = row.locator("td").nth(3).locator(".badge")
    expect(status).to_have_text("recording")
    recording = Recording.objects.get()
    assert recording.topics == ["/chatter"] and recording.max_duration_s == 120
    # While it records, the page polls the list; the Delete button waits until it has ended.
    expect(row.get_by_role("button", name=re.compile("^Delete"))).to_have_count(0)
    page.wait_for_timeout(1500)  # ~30 messages at 20 Hz
    row.get_by_role("button", name="Stop the recording of /chatter").click()
    expect(status).to_have_text("finished", timeout=30_000)
    expect(page.locator("#recording-result")).to_contain_text("The recording of /chatter finished (stopped)")
    messages = int(row.locator("td").nth(4).inner_text())
    assert messages > 0
    link = row.get_by_role("link", name="Download .mcap")
    href = link.get_attribute("href")
    assert href == f"/api/robot/alice-bot/recordings/{recording.id.hex}/download"
    expect(row.locator("td").nth(6)).not_to_have_text("0\u00a0bytes")
    browser.screenshot("robot-recordings")

    # None runs now, so the page stops asking.
    polled: list[str] = []
    page.on("request", lambda request: "/recordings" in request.url and polled.append(request.url))
    page.wait_for_timeout(2500)
    assert polled == []

    # The file, read through the page's session, opens with the mcap reader and holds what the table says.
    download = page.request.get(browser.base_url + href)
    assert download.ok, download.status
    reader = make_reader(io.BytesIO(download.body()))
    assert reader.get_header().profile == "ros1"
    read = list(reader.iter_messages())
    assert len(read) == messages and {channel.topic for _, channel, _ in read} == {"/chatter"}

    # Deleting asks once more; then the row and the file are gone.
    folder = Path(Recording.objects.get().folder)
    assert (folder / "recording.mcap").is_file()
    row.get_by_role("button", name=re.compile(r"^Delete the recording of \/chatter from ")).click()
    row.get_by_role("button", name="Cancel").click()
    expect(row).to_have_count(1)
    row.get_by_role("button", name=re.compile(r"^Delete the recording of \/chatter from ")).click()
    row.get_by_role("button", name="Delete the recording of /chatter for good").click()
    expect(row).to_have_count(0)
    expect(page.locator("#recordings-empty")).to_be_visible()
    expect(page.locator("#recording-result")).to_have_text("Deleted the recording of /chatter.")
    assert not Recording.objects.exists()
    wait_until(lambda: not folder.exists(), what="the recording's folder removed")


def test_bad_input_or_an_offline_robot_shows_the_apis_answer_and_creates_nothing(browser):
    alice = make_user("alice")
    make_robot(alice, "alice-bot", sample=None)
    browser.login("alice")
    page = browser.visit("/robots/alice-bot/")
    browser.expect_http_error(400)

    start(page, "chatter")
    error_shown(page, "Topics", "chatter: An absolute ROS topic name")
    start(page, "")
    error_shown(page, "Topics", "at least 1")
    start(page, "/chatter /chatter")
    error_shown(page, "Topics", "Name each topic once")
    start(page, "/chatter", mib="0.0001")
    error_shown(page, "Max size (MiB)", "greater than or equal to 1024")
    expect(field(page, "Topics")).not_to_have_attribute("aria-invalid", "true")
    start(page, "/chatter", seconds="0")
    error_shown(page, "Max duration (s)", "greater than or equal to 0.1")
    start(page, "/chatter", mib="1", seconds="1e9")
    error_shown(page, "Max duration (s)", "less than or equal to")
    expect(field(page, "Max size (MiB)")).to_have_value("1")  # what was typed stays

    # Valid, but the robot is offline: the API's 409, in the summary.
    browser.expect_http_error(409)
    start(page, "/chatter", mib="1", seconds="5", ros="ros1")
    error_shown(page, None, "alice-bot is offline")
    expect(field(page, "ROS")).to_have_value("ros1")
    assert not Recording.objects.exists()
    expect(page.locator("#recordings-empty")).to_be_visible()


def test_another_user_can_neither_see_nor_act_on_a_recording(browser):
    alice = make_user("alice")
    make_robot(alice, "alice-bot", sample=None)
    recording = Recording.objects.create(
        robot_id="alice-bot", topics=["/chatter"], status="finished", max_bytes=1024, max_duration_s=1
    )
    make_user("bob")
    browser.login("bob")
    browser.expect_http_error(404)
    response = browser.page.goto(browser.base_url + "/robots/alice-bot/")
    assert response is not None and response.status == 404
    assert browser.page.locator("#recording-form").count() == 0
    base = f"/api/robot/alice-bot/recordings/{recording.id.hex}"
    statuses = browser.page.evaluate(
        """async (base) => {
            const csrf = document.cookie.match(/csrftoken=([^;]+)/)?.[1] ?? "";
            const call = async (method, url, body) => (await fetch(url, {
                method, headers: {"X-CSRFToken": csrf, "Content-Type": "application/json"},
                body: body ? JSON.stringify(body) : undefined,
            })).status;
            return [
                await call("GET", "/api/robot/alice-bot/recordings"),
                await call("POST", "/api/robot/alice-bot/recordings", {topics: ["/chatter"]}),
                await call("GET", base),
                await call("POST", base + "/stop"),
                await call("GET", base + "/download"),
                await call("DELETE", base),
            ];
        }""",
        base,
    )
    assert statuses == [404] * 6
    assert list(Recording.objects.values_list("id", flat=True)) == [recording.id]

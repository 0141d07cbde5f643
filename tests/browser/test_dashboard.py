"""The operator dashboard in a real Chromium against daphne, PostgreSQL, Redis and robot agents."""

from __future__ import annotations

import json
import re
import time
from concurrent.futures import ThreadPoolExecutor

import pytest

from bridgeos_agent.protocol import OffloadingDecision
from bridgeos_agent.skillconfig import load_sample_skill_config
from monitoring.services import record_event
from robots.models import Robot
from skills.models import Component, Skill
from skills.services import create_template, report_offloading_decision

from .conftest import AGENT_SKILL, SKILL, make_fleet, make_robot, make_user, start_skill, wait_until

pytestmark = [pytest.mark.browser, pytest.mark.django_db(transaction=True)]
expect = pytest.importorskip(
    "playwright.sync_api", reason="playwright is not installed: pip install -e '.[test]'"
).expect

# Keeps every frame the page's WebSocket receives, to show what never reached it.
RECORD_FRAMES = """
window.__frames = [];
const NativeWebSocket = window.WebSocket;
window.WebSocket = class extends NativeWebSocket {
  constructor(...args) {
    super(...args);
    this.addEventListener("message", (event) => window.__frames.push(event.data));
  }
};
"""


def row(page, robot_id: str):
    return page.locator(f'tr[data-robot="{robot_id}"]')


# --------------------------------------------------------------------------- login


def test_an_operator_logs_in_and_out(browser):
    make_user("alice")
    page = browser.visit("/")
    expect(page).to_have_url(re.compile(r"/accounts/login/\?next=/$"))
    page.get_by_label("Username").fill("alice")
    page.get_by_label("Password").fill("not-her-password")
    page.get_by_role("button", name="Log in").click()
    expect(page.get_by_role("alert")).to_contain_text("didn't match")
    expect(page.get_by_label("Password")).to_have_attribute("aria-invalid", "true")
    browser.screenshot("login")

    browser.login("alice")
    expect(page.get_by_role("heading", name="Fleet")).to_be_visible()
    expect(page.get_by_role("navigation", name="Main").get_by_role("link", name="Fleet")).to_have_attribute(
        "aria-current", "page"
    )
    page.get_by_role("button", name="Log out").click()
    expect(page).to_have_url(re.compile(r"/accounts/login/$"))
    page.goto(browser.base_url + "/skills/")
    expect(page).to_have_url(re.compile(r"/accounts/login/\?next=/skills/$"))


# --------------------------------------------------------------------------- fleet overview


def test_a_robot_appears_online_the_moment_its_agent_connects_and_offline_when_it_stops(browser, agents):
    alice = make_user("alice")
    token = make_robot(alice, "alice-bot", sample="demo_telemetry")
    browser.login("alice")
    page = browser.page
    page.evaluate("window.__sameDocument = true")
    expect(row(page, "alice-bot").locator(".c-conn .badge")).to_have_text("offline")
    expect(row(page, "alice-bot").locator(".c-cpu .value")).to_have_text("—")

    agents.start("alice-bot", token, wait=False)
    expect(row(page, "alice-bot").locator(".c-conn .badge")).to_have_text("online")
    # Live metrics from the agent's monitor, and the Skill it starts: three components on the robot.
    expect(row(page, "alice-bot").locator(".c-cpu .value")).to_have_text(re.compile(r"^\d+(\.\d)?%$"))
    expect(row(page, "alice-bot").locator(".c-battery .value")).to_have_text(re.compile(r"%$"))
    start_skill(browser.base_url, alice, "alice-bot", AGENT_SKILL)
    expect(row(page, "alice-bot").locator(".c-comp .loc.robot")).to_have_text("3")
    expect(row(page, "alice-bot").locator(".c-comp .loc.cloud")).to_have_text("0")
    expect(row(page, "alice-bot").locator(".c-mode")).to_have_text("auto")

    # A robot added after the page loaded shows up as soon as its agent connects.
    second = make_robot(alice, "alice-two", sample=None)
    agents.start("alice-two", second)
    expect(row(page, "alice-two").locator(".c-conn .badge")).to_have_text("online")
    expect(page.locator("#fleet-summary")).to_contain_text("2 online")
    expect(page.locator("#fleet")).to_have_attribute("aria-rowcount", "3")
    browser.screenshot("fleet")

    agents.stop("alice-two")
    expect(row(page, "alice-two").locator(".c-conn .badge")).to_have_text("offline")
    expect(page.locator("#fleet-summary")).to_contain_text("1 offline")
    assert page.evaluate("window.__sameDocument") is True, "the page reloaded"


def test_the_fleet_page_sorts_and_searches_the_whole_fleet_a_page_at_a_time(browser):
    make_fleet(make_user("ops", staff=True), 300)
    browser.login("ops")
    page = browser.page
    rows = page.locator("#fleet-rows tr[data-robot]")
    expect(page.locator("#fleet")).to_have_attribute("aria-rowcount", "301")
    expect(rows.first).to_have_attribute("data-robot", "fleet-0000")
    expect(rows).to_have_count(100)

    # Sorted by the cloud: by id, descending, the fleet's last robot heads the first page.
    page.get_by_role("button", name="Robot").click()
    expect(rows.first).to_have_attribute("data-robot", "fleet-0299")
    expect(rows.first).to_have_attribute("aria-rowindex", "2")
    expect(page.locator('th[data-sort="id"]')).to_have_attribute("aria-sort", "descending")
    page.evaluate("window.scrollTo(0, document.body.scrollHeight)")
    expect(row(page, "fleet-0200")).to_be_visible()
    expect(row(page, "fleet-0200")).to_have_attribute("aria-rowindex", "101")

    page.get_by_label("Search").fill("fleet-012")
    expect(rows).to_have_count(10)
    expect(rows.first).to_have_attribute("data-robot", "fleet-0129")
    expect(page).to_have_url(re.compile(r"/\?q=fleet-012&sort=-id$"))

    page.set_viewport_size({"width": 390, "height": 844})
    page.get_by_label("Search").fill("")
    page.evaluate("window.scrollTo(0, 0)")
    expect(row(page, "fleet-0299")).to_be_visible()
    browser.screenshot("fleet-phone", full_page=False)


# --------------------------------------------------------------------------- robot page


def test_migrating_a_component_changes_its_location_badge(browser, agents):
    alice = make_user("alice")
    token = make_robot(alice, "alice-bot", sample="demo_telemetry")
    agents.start("alice-bot", token)
    browser.login("alice")
    page = browser.visit("/robots/alice-bot/")
    browser.wait_live()
    location = page.locator(f'[data-location="{AGENT_SKILL}/filter"]')
    status = page.locator(f'[data-status="{AGENT_SKILL}/filter"]')
    migrate = page.locator(f'[data-migrate="{AGENT_SKILL}/filter"]')
    expect(location).to_have_text("not placed")

    page.get_by_role("button", name=f"Start skill {AGENT_SKILL}").click()
    expect(page.get_by_role("status").filter(has_text=f"Start {AGENT_SKILL}: accepted by the robot")).to_be_visible()
    expect(page.locator(f'[data-skill-status="{AGENT_SKILL}"]')).to_have_text("running")
    expect(location).to_have_text("robot")
    expect(status).to_have_text("running")
    expect(page.locator(f'[data-migrate="{AGENT_SKILL}/sensor"]')).to_be_disabled()
    filter_process = f"{AGENT_SKILL}/filter"
    wait_until(lambda: filter_process in agents.running("alice-bot"), what="the agent to run filter")

    # To the cloud: the cloud's worker runs a copy, then the agent switches to it and stops its own.
    migrate.click()
    expect(location).to_have_text("cloud")
    expect(location).to_have_class(re.compile(r"\bloc-cloud\b"))
    expect(status).to_have_text("running")
    expect(page.locator(f'tr[data-component="{AGENT_SKILL}/filter"] .outcome')).to_have_text("now runs on the cloud")
    wait_until(
        lambda: Component.objects.get(component_id="filter").active_location == "cloud",
        what="the cloud to record the new location",
    )
    expect(migrate).to_have_text("Migrate to robot")
    wait_until(lambda: filter_process not in agents.running("alice-bot"), what="the agent to stop its copy")

    # And back: the robot runs it again before the cloud copy is stopped.
    migrate.click()
    expect(page.locator(f'tr[data-component="{AGENT_SKILL}/filter"] .outcome')).to_have_text("now runs on the robot")
    wait_until(
        lambda: Component.objects.get(component_id="filter").active_location == "robot",
        what="the cloud to record the robot as the location again",
    )
    expect(location).to_have_text("robot")
    expect(status).to_have_text("running")
    expect(migrate).to_have_text("Migrate to cloud")
    wait_until(lambda: filter_process in agents.running("alice-bot"), what="the agent to run filter again")

    # Stopping and starting the Skill: the robot's answer, then its statuses, show up in place.
    page.get_by_role("button", name=f"Stop skill {AGENT_SKILL}").click()
    expect(page.get_by_role("status").filter(has_text=f"Stop {AGENT_SKILL}: accepted by the robot")).to_be_visible()
    expect(page.locator(f'[data-skill-status="{AGENT_SKILL}"]')).to_have_text("stopped")
    expect(page.locator(f'[data-status="{AGENT_SKILL}/planner"]')).to_have_text("stopped")
    wait_until(lambda: not agents.running("alice-bot"), what="the agent to stop the Skill's processes")
    page.get_by_role("button", name=f"Start skill {AGENT_SKILL}").click()
    expect(page.locator(f'[data-skill-status="{AGENT_SKILL}"]')).to_have_text("running")
    expect(page.locator(f'[data-status="{AGENT_SKILL}/planner"]')).to_have_text("running")
    expect(location).to_have_text("robot")

    # Live charts of the robot and of each component the agent measures.
    expect(page.locator("#robot-charts canvas").first).to_be_visible()
    page.locator("#component-charts").scroll_into_view_if_needed()
    expect(page.locator("#component-charts canvas").first).to_be_visible()
    page.get_by_text("More robot metrics").click()
    expect(page.locator("#more-robot-charts figure", has_text="net_rx")).to_be_visible()
    expect(page.locator("#more-robot-charts canvas").first).to_be_visible()
    page.set_viewport_size({"width": 1280, "height": 3200})
    time.sleep(1.5)  # let charts that came on screen draw
    browser.screenshot("robot")


def test_the_robot_page_lists_the_latest_offloading_decisions(browser, simulated_robots):
    # A simulated robot streams decisions to stay; the moves a Skill Manager logs arrive as events.
    alice = make_user("alice")
    token = make_robot(alice, "alice-bot")
    simulated_robots.start("alice-bot", token)
    browser.login("alice")
    page = browser.visit("/robots/alice-bot/")
    browser.wait_live()
    expect(page.locator(f'[data-location="{SKILL}/sampler"]')).to_have_text("robot")
    expect(page.locator("#decisions tbody tr").first).to_be_visible(timeout=20_000)
    expect(page.locator("#decisions tbody tr").first).to_contain_text(re.compile(r"sampler|detector"))
    # Logged through the same service the robot door calls: it reaches the open page live...
    move = {
        "skill": SKILL,
        "component": "detector",
        "location": "robot",
        "target": "cloud",
        "outcome": "moved",
        "reason": "estimate above threshold + hysteresis",
        "policy": "performance",
        "cost_robot": 0.9,
        "cost_cloud": 0.2,
        "estimated_reward": 0.7,
        "threshold": 0.2,
        "hysteresis": 0.05,
        "trained": False,
        "samples_seen": 40,
        "inputs": {"cpu_available": 0.1, "location": "robot"},
        "decided_by": "network",
        "network_error": 0.04,
        "estimate_error": 0.5,
        "decided_at": time.time(),
        "duration_s": 0.5,
    }
    # In a thread of its own: Playwright's loop runs in this one, and the service broadcasts with async_to_sync.
    with ThreadPoolExecutor(1) as pool:
        pool.submit(report_offloading_decision, "alice-bot", OffloadingDecision.model_validate(move)).result()
    moved = page.locator('#decisions tbody tr[data-outcome="moved"]')
    expect(moved).to_contain_text("moved → cloud")
    expect(moved).to_contain_text("detector")
    # Who decided, and why the network was trusted: its held-out error against the estimate's.
    expect(moved.locator('[data-decided-by="network"]')).to_contain_text("by the learned network (error 0.04 vs 0.5)")
    page.locator("#decisions").scroll_into_view_if_needed()
    browser.screenshot("robot-decisions", full_page=False)
    # ... and is read back from the event log on the next visit, beside the decisions to stay.
    page.reload()
    browser.wait_live()
    expect(moved).to_contain_text("moved → cloud")
    expect(page.locator('#decisions tbody tr[data-outcome="stay"]').first).to_be_visible(timeout=20_000)


def test_a_command_to_an_offline_robot_says_so(browser):
    alice = make_user("alice")
    make_robot(alice, "alice-bot")
    browser.login("alice")
    browser.expect_http_error(409)
    page = browser.visit(f"/robots/alice-bot/#skill-{SKILL}")
    page.get_by_role("button", name=f"Start skill {SKILL}").click()
    expect(page.get_by_role("alert").filter(has_text="offline")).to_be_visible()


def test_robot_config_edits_are_checked_field_by_field_then_stored(browser):
    alice = make_user("alice")
    make_robot(alice, "alice-bot")
    browser.login("alice")
    page = browser.visit("/robots/alice-bot/")
    browser.wait_live()
    heartbeat = page.locator('input[data-path="heartbeat_interval"]')
    heartbeat.fill("500")
    page.locator('input[data-path="resources.cpu"]').fill("-1")
    page.get_by_role("button", name="Save and send to the robot").click()
    expect(page.locator('input[data-path="heartbeat_interval"] + .field-error')).to_contain_text(
        "less than or equal to 300"
    )
    expect(page.locator('input[data-path="resources.cpu"] + .field-error')).to_contain_text(
        "greater than or equal to 0"
    )
    expect(heartbeat).to_have_attribute("aria-invalid", "true")
    expect(page.locator("#config-form .error-summary")).to_contain_text("2 problems")
    browser.screenshot("robot-config-errors")
    assert Robot.objects.get(id="alice-bot").config["heartbeat_interval"] == 5.0

    heartbeat.fill("2")
    page.locator('input[data-path="resources.cpu"]').fill("4")
    page.locator('select[data-path="offloading"]').select_option("manual")
    page.get_by_role("button", name="Save and send to the robot").click()
    expect(page.locator("#config-result")).to_contain_text("Saved")
    expect(page.locator(".field-error")).to_have_count(0)
    expect(page.locator("#robot-offloading")).to_have_text("manual")
    config = Robot.objects.get(id="alice-bot").config
    assert (config["heartbeat_interval"], config["resources"]["cpu"], config["offloading"]) == (2.0, 4.0, "manual")


# --------------------------------------------------------------------------- skill catalog


def test_an_invalid_skill_config_upload_shows_each_error_at_its_field(browser, tmp_path):
    alice = make_user("alice")
    make_robot(alice, "alice-bot", sample=None)
    config = load_sample_skill_config().model_dump(mode="json")
    config["components"]["detector"]["resources"]["cpu"] = -2
    del config["components"]["sampler"]["location"]
    upload = tmp_path / "people.json"
    upload.write_text(json.dumps(config, indent=2))
    browser.login("alice")
    page = browser.visit("/skills/")
    page.get_by_label("Config file").set_input_files(upload)

    cpu = page.locator('[data-path="components.detector.resources.cpu"]')
    expect(cpu).to_have_class(re.compile(r"\binvalid\b"))
    expect(cpu.locator(".field-error")).to_contain_text("greater than or equal to 0")
    expect(page.locator('[data-path="components.sampler.location"].missing .field-error')).to_contain_text(
        "this field is required"
    )
    expect(page.locator("#upload-report .error-summary")).to_contain_text("2 problems")
    expect(page.locator("#upload-actions")).to_be_hidden()
    browser.screenshot("skills-upload-errors")

    fixed = tmp_path / "people-fixed.json"
    fixed.write_text(json.dumps(load_sample_skill_config().model_dump(mode="json")))
    page.get_by_label("Config file").set_input_files(fixed)
    expect(page.locator("#upload-result")).to_contain_text("Valid: People detection (people-detection)")
    page.locator("#upload-add").get_by_role("button", name="Add to robot").click()
    expect(page.locator("#upload-add .result")).to_contain_text("Added people-detection to alice-bot")
    assert Skill.objects.filter(robot_id="alice-bot", skill_id=SKILL).exists()

    # The same again: the cloud refuses a second skill with that id, and says why.
    browser.expect_http_error(400)
    page.locator("#upload-add").get_by_role("button", name="Add to robot").click()
    expect(page.locator("#upload-add .result")).to_contain_text("already has a skill")


def test_a_template_is_added_to_a_robot_from_the_catalog(browser):
    alice = make_user("alice")
    make_robot(alice, "alice-bot", sample=None)
    template = create_template(
        name="People detection", config=load_sample_skill_config().model_dump(mode="json"), tags=["vision"]
    )
    browser.login("alice")
    page = browser.visit("/skills/")
    card = page.locator(f'[data-template="{template.pk}"]')
    expect(card).to_contain_text("Detector · either")
    card.get_by_role("button", name="Add").click()
    expect(card.locator(".result")).to_contain_text("Added people-detection to alice-bot")
    assert Skill.objects.get(robot_id="alice-bot").components.count() == 3
    browser.screenshot("skills")


# --------------------------------------------------------------------------- who sees what


def test_another_user_sees_neither_the_robot_nor_its_live_frames(browser, agents):
    alice = make_user("alice")
    bob = make_user("bob")
    token = make_robot(alice, "alice-bot", sample="demo_telemetry")
    make_robot(bob, "bob-bot", sample=None)
    browser.page.add_init_script(RECORD_FRAMES)
    browser.login("bob")
    page = browser.page
    expect(row(page, "bob-bot")).to_be_visible()

    agents.start("alice-bot", token)
    start_skill(browser.base_url, alice, "alice-bot", AGENT_SKILL)
    wait_until(
        lambda: Component.objects.filter(skill__robot_id="alice-bot", status="running").count() == 3,
        what="alice's robot to run its Skill",
    )
    time.sleep(1.0)  # a few rounds of the live feed
    frames = page.evaluate("window.__frames")
    assert any('"authentication_success"' in frame for frame in frames)
    assert not [frame for frame in frames if "alice-bot" in frame]
    assert row(page, "alice-bot").count() == 0
    assert "alice-bot" not in page.content()
    assert page.request.get(browser.base_url + "/robots/alice-bot/").status == 404
    assert page.request.get(browser.base_url + "/api/robot/alice-bot").status == 404
    browser.screenshot("fleet-other-user")


# --------------------------------------------------------------------------- events and logs


def test_the_event_log_filters_and_tails_live(browser, agents):
    alice = make_user("alice")
    token = make_robot(alice, "alice-bot", sample="demo_telemetry")
    make_robot(alice, "alice-two", sample=None)
    record_event(
        "Planner crashed", robot_id="alice-bot", level="error", skill=AGENT_SKILL, component="planner", kind="test"
    )
    browser.login("alice")
    page = browser.visit("/events/")
    rows = page.locator("#event-rows tr")
    expect(rows.first).to_be_visible()
    expect(page.locator("#event-rows")).to_contain_text("Robot alice-two created")

    page.get_by_label("Level at least").select_option("error")
    page.get_by_role("button", name="Apply filters").click()
    expect(rows).to_have_count(1)
    expect(rows.first).to_contain_text("Planner crashed")
    expect(page).to_have_url(re.compile(r"level=error"))

    page.get_by_label("Level at least").select_option("")
    page.get_by_label("Robot", exact=True).select_option("alice-two")
    page.get_by_role("button", name="Apply filters").click()
    expect(rows).to_have_count(1)
    expect(rows.first).to_contain_text("Robot alice-two created")

    page.get_by_label("Robot", exact=True).select_option("alice-bot")
    page.get_by_label("Component").fill("planner")
    page.get_by_role("button", name="Apply filters").click()
    expect(rows).to_have_count(1)
    page.get_by_label("Component").fill("")
    page.get_by_role("button", name="Apply filters").click()
    expect(rows).to_have_count(3)
    expect(page.locator("#event-rows")).to_contain_text(f"Skill {AGENT_SKILL} added")

    # Live tail: what the robot does appears on top, without a reload.
    agents.start("alice-bot", token, wait=False)
    expect(page.locator("#event-rows tr", has_text="Robot alice-bot connected")).to_have_count(1)
    start_skill(browser.base_url, alice, "alice-bot", AGENT_SKILL)
    # Live, at the top with the robot's other news (its cloud relay may report just after it).
    expect(page.locator("#event-rows tr", has_text=f"Skill {AGENT_SKILL} is running")).to_have_count(1)
    browser.screenshot("events")

    # A time range: an hour long in 2001 holds nothing; the last ten minutes hold the robot's events.
    page.get_by_label("Until").fill("2001-01-01T00:00:00")
    page.get_by_role("button", name="Apply filters").click()
    expect(page.locator("#event-count")).to_have_text("No event matches the filters.")
    page.get_by_label("Until").fill("")
    page.get_by_label("From").fill(time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(time.time() - 600)))
    page.get_by_role("button", name="Apply filters").click()
    expect(page.locator("#event-rows tr", has_text="Robot alice-bot connected")).to_have_count(1)

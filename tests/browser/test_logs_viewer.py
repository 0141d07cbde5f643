"""The dashboard's log viewer (issue 36) in a real Chromium against daphne, PostgreSQL and Redis."""

from __future__ import annotations

import shutil
import subprocess
import time
from concurrent.futures import ThreadPoolExecutor
from datetime import UTC, datetime
from pathlib import Path
from typing import Any
from urllib.parse import parse_qs, urlsplit

import pytest
from django.db import connections

from logs.services import store_lines as store_lines_here
from skills.services import report_component_status

from .conftest import ROOT, make_robot, make_user

pytestmark = [pytest.mark.browser, pytest.mark.django_db(transaction=True)]
expect = pytest.importorskip(
    "playwright.sync_api", reason="playwright is not installed: pip install -e '.[test]'"
).expect

SKILL = "people-detection"  # the sample Skill make_robot adds: components pointcloud, sampler, detector

# Resolves with the browser's clock (ms) when a line with the marker enters the viewer.
WATCH_FOR_LINE = """
(marker) => {
  const pane = document.getElementById("logs-lines");
  window.__seen = new Promise((resolve) => {
    const observer = new MutationObserver(() => {
      if (pane.textContent.includes(marker)) {
        observer.disconnect();
        resolve(Date.now());
      }
    });
    observer.observe(pane, { childList: true, subtree: true });
  });
}
"""
SCROLL_GAP = "(pane) => pane.scrollHeight - pane.scrollTop - pane.clientHeight"


def in_thread(fn, *args, **kwargs):
    """Call a service as the cloud does: from a thread without an event loop (Playwright runs one here)."""

    def call() -> Any:
        try:
            return fn(*args, **kwargs)
        finally:
            # Each call runs in a new thread: its connection goes back to the pool, or the pool runs dry.
            connections.close_all()

    with ThreadPoolExecutor(1) as pool:
        return pool.submit(call).result()


class Printer:
    """Stores lines of a robot's components as the robot door does, each component counting its own seq."""

    def __init__(self, robot_id: str) -> None:
        self.robot_id = robot_id
        self.seqs: dict[tuple[str, str], int] = {}
        self.last_ts = 0.0

    def lines(self, component: str, *texts: str | tuple[str, str | None], ts: float | None = None, **kw: Any) -> int:
        """Store lines (text, or (text, level)) of one component, spread over the last instants before ts."""
        skill = kw.pop("skill", SKILL)
        location = kw.pop("location", "robot")
        # A component's lines follow each other in time, however fast the test stores them.
        now = max(ts if ts is not None else time.time(), self.last_ts + len(texts) * 0.001)
        self.last_ts = now
        batch = []
        for i, item in enumerate(texts):
            text, level = item if isinstance(item, tuple) else (item, None)
            seq = self.seqs[skill, component] = self.seqs.get((skill, component), 0) + 1
            stream = "stderr" if level in ("error", "critical") else "stdout"
            ts_i = now - (len(texts) - 1 - i) * 0.001
            batch.append({"seq": seq, "ts": ts_i, "stream": stream, "level": level, "text": text})
        return in_thread(store_lines_here, self.robot_id, skill, component, location, batch)


def pane(page):
    return page.locator("#logs-lines")


def shown(page) -> list[str]:
    return page.locator("#logs-lines .log-line .txt").all_text_contents()


def open_viewer(browser, path: str) -> Any:
    """Open a page with the viewer and wait until its live tail is subscribed (or it shows a time range)."""
    page = browser.visit(path)
    browser.wait_live()
    expect(page.locator('#logs-state[data-state="live"], #logs-state[data-state="range"]')).to_have_count(1)
    return page


# --------------------------------------------------------------------------- the live tail


def test_a_line_a_component_prints_shows_in_the_live_tail_within_a_second(browser):
    alice = make_user("alice")
    make_robot(alice, "lv-tail")
    printer = Printer("lv-tail")
    printer.lines("detector", "booting the detector", ts=time.time() - 30)
    browser.login("alice")
    page = open_viewer(browser, "/robots/lv-tail/")
    # What was stored before the page opened is its history.
    expect(pane(page)).to_contain_text("booting the detector")
    expect(pane(page).locator(".log-line .src").first).to_have_text(f"{SKILL}/detector")

    latencies = []
    for n in range(3):
        marker = f"frame {n} processed"
        page.evaluate(WATCH_FOR_LINE, marker)
        stored_at = time.time()
        assert printer.lines("detector", marker) == 1
        seen_ms = page.evaluate("window.__seen")
        latencies.append(seen_ms / 1000 - stored_at)
    assert max(latencies) < 1.0, f"lines reached the live tail after {latencies} s"
    expect(page.locator("#logs-state")).to_contain_text("Live · 4 lines")

    # A component's row opens its own logs: the viewer filtered to it, at an address of its own.
    printer.lines("sampler", "sampler says hello")
    expect(pane(page)).to_contain_text("sampler says hello")
    page.get_by_role("link", name="Logs of detector").click()
    page.wait_for_url("**/robots/lv-tail/logs/?skill=people-detection&component=detector")
    browser.wait_live()
    expect(page.locator('#logs-state[data-state="live"]')).to_be_visible()
    expect(page.locator("#logs-scope")).to_have_value(f"{SKILL}/detector")
    expect(pane(page)).to_contain_text("frame 2 processed")
    assert "sampler says hello" not in shown(page)
    printer.lines("sampler", "sampler again")
    printer.lines("detector", "detector again")
    expect(pane(page)).to_contain_text("detector again")
    assert "sampler again" not in shown(page)
    # One component's view needs no source column.
    expect(pane(page).locator(".src")).to_have_count(0)
    browser.screenshot("logs-component")


def test_follow_keeps_the_newest_line_in_view_and_pause_holds_lines_until_resumed(browser):
    alice = make_user("alice")
    make_robot(alice, "lv-follow")
    printer = Printer("lv-follow")
    printer.lines("detector", *[f"history line {i}" for i in range(300)], ts=time.time() - 5)
    browser.login("alice")
    page = open_viewer(browser, "/robots/lv-follow/logs/")
    lines = pane(page)
    expect(lines.locator(".log-line")).to_have_count(300)
    assert lines.evaluate(SCROLL_GAP) < 5, "the viewer opens at its newest line"

    # Following: every new line scrolls into view.
    printer.lines("detector", *[f"followed {i}" for i in range(20)])
    expect(lines.locator(".log-line")).to_have_count(320)
    page.wait_for_function(
        "() => { const p = document.getElementById('logs-lines'); return p.scrollHeight - p.scrollTop - p.clientHeight < 5; }"
    )

    # The reader scrolls up to read: following stops, new lines come in below without moving the view.
    lines.hover()
    page.mouse.wheel(0, -1500)
    expect(page.get_by_label("Follow")).not_to_be_checked()
    top = lines.evaluate("(pane) => pane.scrollTop")
    printer.lines("detector", *[f"unfollowed {i}" for i in range(20)])
    expect(lines.locator(".log-line")).to_have_count(340)
    assert abs(lines.evaluate("(pane) => pane.scrollTop") - top) < 2
    assert lines.evaluate(SCROLL_GAP) > 100
    page.get_by_label("Follow").check()
    assert lines.evaluate(SCROLL_GAP) < 5

    # Paused: lines that arrive are kept and counted, not shown.
    page.get_by_role("button", name="Pause").click()
    expect(page.locator("#logs-state")).to_have_attribute("data-state", "paused")
    printer.lines("detector", *[f"while paused {i}" for i in range(5)])
    expect(page.locator("#logs-state")).to_have_text("Paused · 5 new lines")
    printer.lines("sampler", ("sampler failed to read", "error"))
    expect(page.locator("#logs-state")).to_have_text("Paused · 6 new lines")
    assert not any("while paused" in text for text in shown(page))
    expect(lines.locator(".log-line")).to_have_count(340)
    browser.screenshot("logs-paused")

    # Resumed: they show, in order, and the view is at the newest again.
    page.get_by_role("button", name="Resume").click()
    expect(lines.locator(".log-line")).to_have_count(346)
    texts = shown(page)
    assert texts[-6:] == [*[f"while paused {i}" for i in range(5)], "sampler failed to read"]
    expect(page.locator("#logs-state")).to_have_attribute("data-state", "live")
    page.wait_for_function(
        "() => { const p = document.getElementById('logs-lines'); return p.scrollHeight - p.scrollTop - p.clientHeight < 5; }"
    )
    expect(lines.locator(".log-line.lv-error")).to_have_count(1)


def test_a_chatty_component_keeps_at_most_5000_lines_in_the_page(browser):
    alice = make_user("alice")
    make_robot(alice, "lv-chatty")
    printer = Printer("lv-chatty")
    browser.login("alice")
    page = open_viewer(browser, "/robots/lv-chatty/logs/")
    for burst in range(6):
        printer.lines("sampler", *[f"sample {burst * 1000 + i}" for i in range(1000)])
    lines = pane(page).locator(".log-line")
    expect(pane(page)).to_contain_text("sample 5999")
    expect(lines).to_have_count(5000)
    texts = shown(page)
    assert texts[0] == "sample 1000" and texts[-1] == "sample 5999"
    assert texts == [f"sample {n}" for n in range(1000, 6000)], "in order, each once"
    # What left the page is one click away again.
    expect(page.get_by_role("button", name="Load older lines")).to_be_visible()


def test_level_text_and_time_filters_narrow_the_lines_and_the_download(browser):
    alice = make_user("alice")
    make_robot(alice, "lv-filter")
    printer = Printer("lv-filter")
    start = time.time() - 600
    # 600 old lines (older pages), then a few of each level.
    printer.lines("pointcloud", *[f"cloud point {i}" for i in range(600)], ts=start)
    printer.lines(
        "detector",
        ("loading weights", "debug"),
        ("disk usage 40%", None),
        ("disk low: 9% left", "warning"),
        ("disk full", "error"),
        ("camera lost", "critical"),
        ts=start + 60,
    )
    browser.login("alice")
    page = open_viewer(browser, "/robots/lv-filter/logs/")
    lines = pane(page).locator(".log-line")
    # A page of the newest 500; the older ones one click away (the API's cursor).
    expect(lines).to_have_count(500)
    page.get_by_role("button", name="Load older lines").click()
    expect(lines).to_have_count(605)
    expect(page.get_by_role("button", name="Load older lines")).to_be_hidden()
    assert shown(page)[0] == "cloud point 0"

    # Minimum level: warning and above (a line without a level counts as info).
    page.get_by_label("Level at least").select_option("warning")
    expect(lines).to_have_count(3)
    assert shown(page) == ["disk low: 9% left", "disk full", "camera lost"]
    # Live lines pass the same filters.
    printer.lines("detector", ("disk fine again", "info"), ("disk on fire", "error"))
    expect(lines).to_have_count(4)
    assert "disk fine again" not in shown(page)

    # Text: a substring, any case; then a regular expression; a bad one is refused naming the field.
    page.get_by_label("Text", exact=True).fill("DISK")
    page.get_by_role("button", name="Apply filters").click()
    expect(lines).to_have_count(3)
    assert shown(page) == ["disk low: 9% left", "disk full", "disk on fire"]
    page.get_by_label("Text", exact=True).fill("^disk (full|on)")
    page.get_by_label("Text is a regular expression").check()
    page.get_by_role("button", name="Apply filters").click()
    expect(lines).to_have_count(2)
    assert page.url.endswith("/logs/?level=warning&q=%5Edisk+%28full%7Con%29&regex=true")
    download = page.locator("#logs-download").get_attribute("href")
    response = page.request.get(browser.base_url + download)
    assert response.status == 200, response.text()
    body = response.text().splitlines()
    assert [line.split(": ", 1)[1] for line in body] == ["disk full", "disk on fire"], body
    assert f"robot stderr ERROR {SKILL}/detector: disk full" in body[0]
    page.get_by_label("Text", exact=True).fill("(disk")
    page.get_by_role("button", name="Apply filters").click()
    expect(page.get_by_label("Text", exact=True)).to_have_attribute("aria-invalid", "true")
    expect(page.locator("#logs-q-error")).to_contain_text("not a regular expression")
    expect(lines).to_have_count(2)  # nothing changed

    # A time range reads back: only its lines, and no live tail.
    page.get_by_role("button", name="Clear").click()
    expect(page.get_by_label("Text", exact=True)).to_have_value("")
    since = datetime.fromtimestamp(start + 59, UTC).strftime("%Y-%m-%dT%H:%M:%S")
    until = datetime.fromtimestamp(start + 61, UTC).strftime("%Y-%m-%dT%H:%M:%S")
    page.get_by_label("From").fill(since)
    page.get_by_label("Until").fill(until)
    page.get_by_role("button", name="Apply filters").click()
    expect(page.locator("#logs-state")).to_have_attribute("data-state", "range")
    expect(lines).to_have_count(5)
    assert shown(page)[0] == "loading weights"
    printer.lines("detector", "after the range")
    time.sleep(1)
    assert "after the range" not in shown(page)
    query = parse_qs(urlsplit(page.locator("#logs-download").get_attribute("href")).query)
    assert query["since"] == [f"{since}.000Z"] and query["until"] == [f"{until}.000Z"]
    browser.screenshot("logs-range")


# --------------------------------------------------------------------------- crashes


def record_crash(robot_id: str, component: str, lines: list[dict[str, Any]]) -> None:
    """Report a component's crash with its last lines, as the robot door does for a status report."""
    in_thread(report_component_status, robot_id, SKILL, component, "failed", "robot", "exited with 3", last_lines=lines)


def test_a_crash_event_shows_its_last_lines_one_click_away(browser):
    alice = make_user("alice")
    make_robot(alice, "lv-crash")
    printer = Printer("lv-crash")
    now = time.time()
    printer.lines("detector", *[f"detector step {i}" for i in range(10)], ("Traceback: boom", "error"), ts=now - 2)
    browser.login("alice")
    page = open_viewer(browser, "/robots/lv-crash/")
    crashes = page.locator("#logs-crashes")
    expect(crashes).to_be_hidden()
    last = [
        {"seq": 9 + i, "ts": now - 2 + i * 0.001, "stream": "stdout", "level": None, "text": f"detector step {8 + i}"}
        for i in range(2)
    ]
    last.append({"seq": 11, "ts": now - 1.99, "stream": "stderr", "level": "error", "text": "Traceback: boom"})
    record_crash("lv-crash", "detector", last)

    # The crash arrives live on the robot page; its lines are one click away.
    expect(crashes).to_be_visible()
    crashes.locator("summary").first.click()
    item = crashes.locator("li").first
    expect(item).to_contain_text("Component detector is failed on the robot")
    item.get_by_text("Last 3 lines").click()
    expect(item.locator(".log-line")).to_have_count(3)
    expect(item.locator(".log-line.lv-error")).to_contain_text("Traceback: boom")
    browser.screenshot("logs-crash")

    # ... and the viewer at the time of the crash, one more.
    item.get_by_role("link", name="Open in the log viewer").click()
    page.wait_for_url("**/robots/lv-crash/logs/?**")
    expect(page.locator("#logs-state")).to_have_attribute("data-state", "range")
    expect(page.locator("#logs-scope")).to_have_value(f"{SKILL}/detector")
    expect(pane(page).locator(".log-line")).to_have_count(11)
    expect(pane(page).locator(".log-line").last).to_contain_text("Traceback: boom")

    # The events page shows the same lines under the event.
    page = browser.visit("/events/")
    row = page.locator("#event-rows tr", has_text="Component detector is failed")
    row.get_by_text("Last 3 lines").click()
    expect(row.locator(".log-line")).to_have_count(3)
    href = row.get_by_role("link", name="Open in the log viewer").get_attribute("href")
    assert href.startswith(f"/robots/lv-crash/logs/?skill={SKILL}&component=detector&since="), href


# --------------------------------------------------------------------------- ownership and the pure parts


def test_another_users_robot_has_no_log_viewer(browser):
    alice = make_user("alice")
    bob = make_user("bob")
    make_robot(alice, "lv-alice", sample=None)
    make_robot(bob, "lv-bob", sample=None)
    Printer("lv-bob").lines("detector", "bob's secret")
    browser.login("alice")
    browser.expect_http_error(404)
    response = browser.page.goto(f"{browser.base_url}/robots/lv-bob/logs/")
    assert response.status == 404
    page = open_viewer(browser, "/robots/lv-alice/logs/")
    # Bob's lines reach neither alice's page nor its live tail.
    Printer("lv-bob").lines("detector", "bob's second secret")
    time.sleep(1)
    assert "secret" not in pane(page).text_content()


def test_the_viewers_rules_pass_their_node_tests():
    node = shutil.which("node")
    if node is None:
        pytest.skip("node is not installed: scripts/services.sh node")
    result = subprocess.run(
        [node, "--test", str(Path(ROOT, "tests", "js", "logviewer"))], capture_output=True, text=True, timeout=60
    )
    assert result.returncode == 0, result.stdout + result.stderr

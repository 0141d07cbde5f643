"""The Rollouts pages: a rollout followed live as the executor moves it, steered by a developer, read-only to a viewer.

The robots are offline, so each one the executor reaches becomes `offline` (the release stored as
its desired version); the test takes the executor's steps itself (`executor.tick()`, the Celery
beat's task), and no Celery worker runs, so nothing else moves the rollout.
"""

from __future__ import annotations

import pytest

from robots.services import create_robot
from rollouts import executor, rolling
from rollouts.models import Rollout, RolloutRobot
from rollouts.services import create_release
from teams.models import Organization
from tests.conftest import wait_until
from tests.rollouts.test_releases import config
from tests.teams.teamutil import team

from .conftest import make_user

pytestmark = [pytest.mark.browser, pytest.mark.django_db(transaction=True)]

expect = pytest.importorskip("playwright.sync_api").expect


@pytest.fixture
def lab() -> Organization:
    """The lab (a developer, a viewer) with four robots, all offline; another team (eve) of its own."""
    dev, _, _ = make_user("dev"), make_user("viewer"), make_user("eve")
    team("other", eve="developer")
    lab = team("lab", dev="developer", viewer="viewer")
    for n in range(4):
        create_robot(f"lab-{n}", dev, organization=lab, labels={"site": "lab"})
    return lab


def start_rollout(lab: Organization) -> Rollout:
    """Roll release #1 of `detect` out to the lab's four robots in batches of 1, 2 and 1."""
    dev = lab.memberships.get(role="developer").user
    release = create_release(lab, config(), user=dev)
    rollout = rolling.create_rollout(release, "site=lab", strategy={"first": 1, "factor": 2}, user=dev)
    assert rollout.batch_sizes == [1, 2, 1]
    return rollout


def status(robot_id: str) -> str:
    return RolloutRobot.objects.get(robot_id=robot_id).status


def test_a_developer_follows_a_rollout_live_and_pauses_resumes_and_aborts_it(browser, lab):
    rollout = start_rollout(lab)
    browser.login("dev")
    page = browser.visit("/rollouts/")
    expect(page.get_by_role("link", name="Rollouts")).to_have_attribute("aria-current", "page")
    row = page.locator(f'tr[data-rollout="{rollout.id}"]')
    expect(row).to_contain_text("detect #1")
    expect(row).to_contain_text("site=lab")
    expect(row.locator('[data-field="state"]')).to_have_text("running")
    expect(row.locator('[data-field="batch"]')).to_have_text("1 of 3")
    expect(row.locator('[data-status="pending"]')).to_have_text("pending 4")
    expect(row).to_contain_text("by dev")
    row.get_by_role("link", name=f"#{rollout.id}").click()
    page.wait_for_url(f"{browser.base_url}/rollouts/{rollout.id}/")

    # A mark on this very document: were the page reloaded, it would be gone.
    page.evaluate("window.sameDocument = true")
    robots = page.locator("#rollout-robots tr")
    expect(robots).to_have_count(4)
    first = page.locator('#rollout-robots tr[data-robot="lab-0"]')
    expect(first).to_have_attribute("data-status", "pending")
    expect(first.get_by_role("link", name="lab-0")).to_have_attribute("href", "/robots/lab-0/")
    expect(page.locator("#rollout-batch")).to_have_text("1 of 3")
    expect(page.locator("#rollout-batches tr")).to_have_count(3)
    expect(page.locator('#rollout-batches tr[data-batch="1"]')).to_have_attribute("data-state", "running")

    executor.tick()  # the canary reached: offline, so it installs when it reconnects; batch 2 starts
    assert status("lab-0") == "offline"
    expect(first).to_have_attribute("data-status", "offline")
    expect(first).to_contain_text("offline: installs when it reconnects")
    expect(page.locator("#rollout-batch")).to_have_text("2 of 3")
    expect(page.locator('#rollout-batches tr[data-batch="1"]')).to_have_attribute("data-state", "done")
    expect(page.locator('#rollout-counts [data-status="offline"]')).to_have_text("offline 1")
    expect(page.locator('#rollout-counts [data-status="pending"]')).to_have_text("pending 3")

    page.get_by_role("button", name="Pause").click()
    expect(page.locator("#rollout-state")).to_have_text("paused")
    expect(page.locator("#rollout-reason")).to_have_text("paused by dev")
    assert Rollout.objects.get(pk=rollout.pk).state == "paused"
    expect(page.get_by_role("button", name="Pause")).to_be_hidden()
    executor.tick()  # a paused rollout does not move
    assert status("lab-1") == "pending"

    page.get_by_role("button", name="Resume").click()
    expect(page.locator("#rollout-state")).to_have_text("running")
    assert Rollout.objects.get(pk=rollout.pk).state == "running"
    executor.tick()
    assert (status("lab-1"), status("lab-2")) == ("offline", "offline")
    expect(page.locator('#rollout-robots tr[data-robot="lab-2"]')).to_have_attribute("data-status", "offline")
    expect(page.locator("#rollout-batch")).to_have_text("3 of 3")

    # An abort asks first; meanwhile another developer aborts it, so this one's is refused with the reason.
    page.get_by_role("button", name="Abort", exact=True).click()
    confirm = page.get_by_role("button", name="Abort the rollout")
    expect(confirm).to_be_visible()
    rolling.steer(Rollout.objects.get(pk=rollout.pk), "abort", "boss")
    browser.expect_http_error(409)
    confirm.click()
    expect(page.locator("#rollout-error")).to_contain_text("only a running or paused rollout is aborted")
    expect(page.locator("#rollout-state")).to_have_text("rolling_back")
    expect(page.locator("#rollout-reason")).to_have_text("aborted by boss")
    for name in ("Pause", "Resume", "Abort"):
        expect(page.get_by_role("button", name=name, exact=True)).to_be_hidden()

    wait_until(lambda: executor.tick() >= 0 and Rollout.objects.get(pk=rollout.pk).state == "aborted", what="abort")
    expect(page.locator("#rollout-state")).to_have_text("aborted")
    assert page.evaluate("window.sameDocument") is True
    browser.screenshot("rollout-aborted")


def test_a_viewer_sees_no_steering_buttons_and_their_pause_is_refused(browser, lab):
    rollout = start_rollout(lab)
    browser.login("viewer")
    page = browser.visit(f"/rollouts/{rollout.id}/")
    expect(page.locator("#rollout-robots tr")).to_have_count(4)
    expect(page.locator("#read-only")).to_be_visible()
    for name in ("Pause", "Resume", "Abort"):
        expect(page.get_by_role("button", name=name, exact=True)).to_have_count(0)
    # The viewer's own session, its CSRF token included: the API refuses the role, not the request.
    browser.expect_http_error(403)
    answer = page.evaluate(
        """async (url) => {
          const token = document.querySelector('meta[name="csrf-token"]').content;
          const response = await fetch(url, {method: "POST", headers: {"X-CSRFToken": token}, credentials: "same-origin"});
          return [response.status, await response.text()];
        }""",
        f"/api/rollouts/{rollout.id}/pause",
    )
    assert answer[0] == 403, answer
    assert Rollout.objects.get(pk=rollout.pk).state == "running"
    # The page still follows the rollout live for the viewer.
    executor.tick()
    expect(page.locator('#rollout-robots tr[data-robot="lab-0"]')).to_have_attribute("data-status", "offline")


def test_another_organizations_user_finds_the_rollout_as_missing(browser, lab):
    rollout = start_rollout(lab)
    browser.login("eve")
    page = browser.visit("/rollouts/")
    expect(page.locator("#no-rollouts")).to_be_visible()
    expect(page.locator(f'tr[data-rollout="{rollout.id}"]')).to_have_count(0)
    browser.expect_http_error(404)
    theirs = page.goto(f"{browser.base_url}/rollouts/{rollout.id}/")
    assert theirs is not None and theirs.status == 404
    body = theirs.text().replace(str(rollout.id), "ID")
    missing_id = rollout.id + 1000
    missing = page.goto(f"{browser.base_url}/rollouts/{missing_id}/")
    assert missing is not None and missing.status == 404
    assert missing.text().replace(str(missing_id), "ID") == body
    assert "detect" not in body and "lab" not in body

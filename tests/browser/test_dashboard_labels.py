"""Robot labels in the dashboard: chips, an admin's edit on the robot page, and the fleet filtered by a selector."""

from __future__ import annotations

import pytest

from robots.models import Robot
from robots.services import create_robot
from teams.models import Membership, Organization

from .conftest import make_user

pytestmark = [pytest.mark.browser, pytest.mark.django_db(transaction=True)]

expect = pytest.importorskip("playwright.sync_api").expect


def lab_fleet() -> Organization:
    """Make a lab (ada admin, otto operator) with three labelled robots, and bob's robot with the same labels."""
    ada, otto, bob = make_user("ada"), make_user("otto"), make_user("bob")
    lab = Organization.objects.create(slug="lab", name="Lab")
    Membership.objects.create(organization=lab, user=ada, role="admin")
    Membership.objects.create(organization=lab, user=otto, role="operator")
    create_robot("lab-1", ada, organization=lab, labels={"site": "lab", "model": "turtlebot"})
    create_robot("lab-2", ada, organization=lab, labels={"site": "field", "model": "turtlebot"})
    create_robot("lab-3", ada, organization=lab)
    create_robot("bob-1", bob, labels={"site": "lab", "model": "turtlebot"})
    return lab


def test_an_admin_edits_a_robots_labels_on_its_page(browser):
    lab_fleet()
    browser.login("ada")
    page = browser.visit("/robots/lab-1/")
    chips = page.locator("#robot-labels .chip")
    expect(chips).to_have_text(["model=turtlebot", "site=lab"])
    field = page.locator("#labels-form").get_by_label("Labels")
    expect(field).to_have_value("model=turtlebot,site=lab")
    save = page.get_by_role("button", name="Save labels")

    field.fill("site=lab,arm=UR5e,gpu=")
    save.click()
    expect(page.locator("#labels-result")).to_have_text("Labels saved.")
    expect(chips).to_have_text(["arm=UR5e", "gpu=", "site=lab"])
    assert Robot.objects.get(id="lab-1").labels == {"site": "lab", "arm": "UR5e", "gpu": ""}

    # A bad key is refused by the cloud, named in the answer, and nothing changes.
    browser.expect_http_error(400)
    field.fill("Site=moon")
    save.click()
    expect(page.locator("#labels-result")).to_contain_text("label key 'Site' is invalid")
    expect(field).to_have_attribute("aria-invalid", "true")
    expect(chips).to_have_text(["arm=UR5e", "gpu=", "site=lab"])
    field.fill("moon")
    save.click()
    expect(page.locator("#labels-result")).to_have_text("label \"moon\" has no '=': write key=value")
    assert Robot.objects.get(id="lab-1").labels == {"site": "lab", "arm": "UR5e", "gpu": ""}

    # Emptied, the robot has no labels.
    field.fill("")
    save.click()
    expect(page.locator("#labels-result")).to_have_text("Labels saved.")
    expect(page.locator("#robot-labels li")).to_have_text(["none"])
    assert Robot.objects.get(id="lab-1").labels == {}


def test_an_operator_sees_the_labels_without_the_form_and_the_cloud_refuses_their_edit(browser):
    lab_fleet()
    browser.login("otto")
    page = browser.visit("/robots/lab-1/")
    expect(page.locator("#robot-labels .chip")).to_have_text(["model=turtlebot", "site=lab"])
    expect(page.locator("#labels-form")).to_have_count(0)
    browser.expect_http_error(403)
    status = page.evaluate(
        """async () => {
          const token = document.cookie.match(/csrftoken=([^;]+)/)?.[1] ?? "";
          const answer = await fetch("/api/robot/lab-1", {
            method: "PATCH", credentials: "same-origin",
            headers: {"Content-Type": "application/json", "X-CSRFToken": token},
            body: JSON.stringify({labels: {site: "moon"}}),
          });
          return answer.status;
        }"""
    )
    assert status == 403
    assert Robot.objects.get(id="lab-1").labels == {"site": "lab", "model": "turtlebot"}


def test_the_fleet_shows_labels_and_its_search_filters_by_a_selector(browser):
    lab_fleet()
    browser.login("otto")
    page = browser.page
    rows = page.locator("#fleet-rows tr[data-robot]")
    expect(rows).to_have_count(3)
    expect(page.locator('#fleet-rows tr[data-robot="lab-2"] .labels .chip')).to_have_text(
        ["model=turtlebot", "site=field"]
    )
    search = page.get_by_label("Search")

    search.fill("site=lab")
    expect(page.locator("#fleet-filter-result")).to_have_text("Label selector: 1 robot(s) match.")
    expect(rows).to_have_count(1)
    expect(page.locator('#fleet-rows tr[data-robot="lab-1"]')).to_have_count(1)  # never bob's robot

    search.fill("model=turtlebot,site!=lab")
    expect(page.locator("#fleet-filter-result")).to_have_text("Label selector: 1 robot(s) match.")
    expect(rows).to_have_count(1)
    expect(page.locator('#fleet-rows tr[data-robot="lab-2"]')).to_have_count(1)

    search.fill("!site")
    # No '=': the text matches ids and names as before.
    expect(rows).to_have_count(0)
    expect(page.locator("#fleet-no-match")).to_be_visible()

    browser.expect_http_error(400)
    search.fill("Site=lab")
    expect(page.locator("#fleet-filter-result")).to_contain_text("selector term 'Site=lab' is invalid")
    expect(rows).to_have_count(0)

    search.fill("lab-")
    expect(page.locator("#fleet-filter-result")).to_have_text("")
    expect(rows).to_have_count(3)

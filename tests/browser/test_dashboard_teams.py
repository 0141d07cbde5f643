"""Teams in the dashboard: buttons by role, the organization picker, members, and API tokens made and revoked."""

from __future__ import annotations

import pytest

from bridgeos_agent.skillconfig import load_sample_skill_config
from robots.models import ApiToken
from robots.services import create_robot
from skills.services import add_skill
from teams.models import Membership, Organization

from .conftest import make_user

pytestmark = [pytest.mark.browser, pytest.mark.django_db(transaction=True)]

expect = pytest.importorskip("playwright.sync_api").expect


def lab_with_robot() -> Organization:
    """Make a lab organization (ada admin, vic viewer) with a robot that has the sample Skill."""
    ada, vic = make_user("ada"), make_user("vic")
    lab = Organization.objects.create(slug="lab", name="Lab")
    Membership.objects.create(organization=lab, user=ada, role="admin")
    Membership.objects.create(organization=lab, user=vic, role="viewer")
    robot, _ = create_robot("lab-bot", ada, organization=lab)
    add_skill(robot, load_sample_skill_config("people_detection").model_dump(mode="json"))
    return lab


def test_a_viewer_sees_the_robot_without_command_buttons(browser):
    lab_with_robot()
    browser.login("vic")
    page = browser.visit("/robots/lab-bot/")
    browser.wait_live()
    skill = page.locator('article[data-skill="people-detection"]')
    expect(skill).to_be_visible()
    expect(page.locator("#read-only")).to_be_visible()
    expect(page.locator("[data-robot-command]")).to_have_count(0)
    expect(skill.get_by_role("button")).to_have_count(0)
    expect(page.locator("#recording-form")).to_have_count(0)
    expect(page.locator("#bridge-urls")).to_have_count(0)
    expect(page.get_by_role("button", name="Save and send to the robot")).to_have_count(0)
    expect(page.locator('#config-form input[name="threshold"]')).to_be_disabled()


def test_an_admin_sees_the_robot_with_its_command_buttons(browser):
    lab_with_robot()
    browser.login("ada")
    page = browser.visit("/robots/lab-bot/")
    browser.wait_live()
    skill = page.locator('article[data-skill="people-detection"]')
    expect(page.locator("[data-robot-command]")).to_have_count(2)
    expect(skill.get_by_role("button", name="Start skill people-detection")).to_be_visible()
    expect(skill.get_by_role("button", name="Remove skill people-detection")).to_be_visible()
    expect(skill.get_by_role("button", name="Migrate").first).to_be_attached()
    expect(page.locator("#recording-form")).to_be_visible()
    expect(page.get_by_role("button", name="Save and send to the robot")).to_be_visible()


def test_picking_an_organization_changes_the_fleet(browser):
    lab = lab_with_robot()
    ada = lab.memberships.get(role="admin").user
    create_robot("home-bot", ada)  # in ada's personal organization
    browser.login("ada")
    page = browser.page
    rows = page.locator("#fleet-rows tr")
    expect(rows).to_have_count(2)
    page.get_by_label("Organization").select_option("lab")
    page.wait_for_url(f"{browser.base_url}/")
    expect(page.get_by_label("Organization")).to_have_value("lab")
    expect(rows).to_have_count(1)
    expect(page.locator('#fleet-rows tr[data-robot="lab-bot"]')).to_have_count(1)
    page.get_by_label("Organization").select_option("ada")
    expect(page.get_by_label("Organization")).to_have_value("ada")
    expect(rows).to_have_count(1)
    expect(page.locator('#fleet-rows tr[data-robot="home-bot"]')).to_have_count(1)
    page.get_by_label("Organization").select_option("")
    expect(page.get_by_label("Organization")).to_have_value("")
    expect(rows).to_have_count(2)


def test_a_member_makes_and_revokes_a_token_in_the_tokens_page(browser):
    lab_with_robot()
    browser.login("vic")
    page = browser.visit("/tokens/")
    form = page.locator("#token-form")
    form.get_by_label("Name").fill("grafana")
    form.get_by_label("Organization").select_option("lab")
    form.get_by_label("Role").select_option("admin")
    browser.expect_http_error(400)
    form.get_by_role("button", name="Make token").click()
    expect(page.get_by_role("alert")).to_contain_text("at most yours here (viewer)")
    assert not ApiToken.objects.filter(name="grafana").exists()
    form.get_by_label("Role").select_option("viewer")
    form.get_by_label("Expires in (days)").fill("30")
    form.get_by_role("button", name="Make token").click()
    key = page.locator("#made-key").input_value()
    assert key.startswith("bat_")
    token = ApiToken.objects.get(name="grafana")
    assert (token.organization.slug, token.role) == ("lab", "viewer")
    row = page.locator(f'#tokens tr[data-token="{token.pk}"]')
    expect(row).to_contain_text("lab")
    # Reloading never shows the key again.
    page.reload()
    expect(page.locator("#made-key")).to_have_count(0)
    page.locator(f'#tokens tr[data-token="{token.pk}"]').get_by_role("button", name="Revoke grafana").click()
    expect(page.locator(f'#tokens tr[data-token="{token.pk}"]')).to_have_count(0)
    assert not ApiToken.objects.filter(pk=token.pk).exists()


def test_an_admin_adds_a_member_and_a_viewer_gets_no_forms(browser):
    lab_with_robot()
    make_user("bob")
    browser.login("ada")
    page = browser.visit("/organizations/lab/")
    form = page.locator("#member-form")
    form.get_by_label("Username").fill("bob")
    form.get_by_label("Role").select_option("operator")
    form.get_by_role("button", name="Add member").click()
    expect(page.locator('#members tr[data-member="bob"] select')).to_have_value("operator")
    browser.expect_http_error(400)
    page.locator('#members tr[data-member="ada"] select').select_option("viewer")
    page.locator('#members tr[data-member="ada"]').get_by_role("button", name="Change role").click()
    expect(page.get_by_role("alert")).to_contain_text("at least one admin")
    assert Membership.objects.get(organization__slug="lab", user__username="ada").role == "admin"
    page.get_by_role("button", name="Log out").click()
    browser.login("vic")
    page = browser.visit("/organizations/lab/")
    expect(page.locator("#member-form")).to_have_count(0)
    expect(page.locator('#members tr[data-member="bob"] [data-role]')).to_have_text("operator")
    expect(page.locator('#members tr[data-member="bob"]').get_by_role("button")).to_have_count(0)

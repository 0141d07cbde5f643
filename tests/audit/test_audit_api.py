"""`GET /api/audit` and the /audit/ page: who reads which entries, filters, pages and exports."""

from __future__ import annotations

import csv
import io
from typing import Any

import pytest
from django.contrib.auth import get_user_model
from django.test import Client

from audit import services
from robots.access import SESSION_ORGANIZATION
from robots.services import issue_api_token
from teams.models import Membership, Organization
from tests.cloud.apiutil import client

pytestmark = pytest.mark.django_db(transaction=True)


@pytest.fixture
def world(daphne_server) -> dict[str, Any]:
    """Two organizations with entries each; acme's admin, acme's viewer, and staff, with their tokens."""
    users = get_user_model().objects
    acme = Organization.objects.create(slug="acme")
    globex = Organization.objects.create(slug="globex")
    keys = {}
    for name, staff in (("carol", False), ("victor", False), ("root", True)):
        keys[name] = issue_api_token(users.create_user(name, is_staff=staff))[0]
    Membership.objects.create(organization=acme, user=users.get(username="carol"), role="admin")
    Membership.objects.create(organization=globex, user=users.get(username="carol"), role="viewer")
    Membership.objects.create(organization=acme, user=users.get(username="victor"), role="viewer")
    for index in range(5):
        services.record(
            "robot.start" if index % 2 else "skill.stop",
            door="rest" if index < 4 else "ws",
            actor="carol",
            target=f"robot/acme-{index % 2}" + ("/skill/s" if index % 2 == 0 else ""),
            status=200 if index else 403,
            organization_id=acme.id,
            organization_slug="acme",
        )
    services.record(
        "robot.delete",
        door="rest",
        actor="gus",
        target="robot/g1",
        organization_id=globex.id,
        organization_slug="globex",
    )
    services.record("login.failed", door="login", actor="nobody", status=401)
    return {"keys": keys, "acme": acme, "globex": globex}


def read(server: Any, key: str, **params: Any) -> Any:
    """Return the answer of GET /api/audit with these parameters."""
    with client(server, key) as http:
        return http.get("/api/audit", params=params)


def test_an_admin_reads_their_organizations_entries_and_no_other(daphne_server, world):
    answer = read(daphne_server, world["keys"]["carol"]).json()
    assert [entry["organization_slug"] for entry in answer["results"]] == ["acme"] * 5  # globex: only a viewer
    assert answer["next"] is None
    assert read(daphne_server, world["keys"]["victor"]).json()["results"] == []  # a viewer of acme
    assert len(read(daphne_server, world["keys"]["root"]).json()["results"]) == 7  # staff: everything


def test_a_token_scoped_to_an_organization_reads_only_there_and_only_as_admin(daphne_server, world):
    carol = get_user_model().objects.get(username="carol")
    as_admin = issue_api_token(carol, organization=world["acme"])[0]
    capped = issue_api_token(carol, organization=world["acme"], role="operator")[0]
    assert len(read(daphne_server, as_admin).json()["results"]) == 5
    assert read(daphne_server, capped).json()["results"] == []


def test_filters_narrow_the_entries(daphne_server, world):
    root = world["keys"]["root"]

    def actions(**params: Any) -> list[str]:
        return [entry["action"] for entry in read(daphne_server, root, **params).json()["results"]]

    assert actions(action="robot.delete") == ["robot.delete"]
    assert len(actions(action="robot.*")) == 3
    assert actions(door="login") == ["login.failed"]
    assert actions(outcome="denied", organization="acme") == ["skill.stop"]
    assert len(actions(robot="acme-0")) == 3  # the robot and its Skill
    assert actions(robot="acme") == []
    assert len(actions(actor="carol")) == 5
    assert len(actions(object="robot/acme-1")) == 2
    newest = read(daphne_server, root).json()["results"][0]["ts"]
    assert actions(since=newest) == ["login.failed"]
    assert len(actions(until=newest)) == 6


@pytest.mark.parametrize(
    ("param", "value"),
    [
        ("since", "yesterday"),
        ("door", "window"),
        ("outcome", "meh"),
        ("limit", "0"),
        ("limit", "5000"),
        ("before", "x"),
        ("format", "xml"),
        ("robot", "a b"),
    ],
)
def test_a_bad_parameter_is_a_400_naming_it(daphne_server, world, param, value):
    answer = read(daphne_server, world["keys"]["root"], **{param: value})
    assert answer.status_code == 400
    assert list(answer.json()) == [param]


def test_pages_follow_next_newest_first(daphne_server, world):
    seen: list[int] = []
    with client(daphne_server, world["keys"]["root"]) as http:
        url: str | None = "/api/audit?limit=3"
        while url:
            page = http.get(url).json()
            seen += [entry["id"] for entry in page["results"]]
            url = page["next"]
    assert len(seen) == 7 and seen == sorted(seen, reverse=True)


def test_csv_and_json_exports_parse_back_to_the_entries(daphne_server, world):
    key = world["keys"]["carol"]
    with client(daphne_server, key) as http:
        exported = http.get("/api/audit", params={"format": "csv", "door": "rest"})
        downloaded = http.get("/api/audit", params={"download": "true"})
    assert exported.headers["content-type"].startswith("text/csv")
    assert "attachment" in exported.headers["content-disposition"]
    rows = list(csv.DictReader(io.StringIO(exported.text)))
    assert len(rows) == 4 and {row["organization_slug"] for row in rows} == {"acme"}
    page = read(daphne_server, key, door="rest").json()["results"]
    assert [row["hash"] for row in rows] == [entry["hash"] for entry in page]
    assert [row["ts"] for row in rows] == [entry["ts"].replace("Z", "+00:00") for entry in page]
    assert downloaded.json() == read(daphne_server, key).json()["results"]


def test_anonymous_readers_are_refused(daphne_server, world):
    assert read(daphne_server, "").status_code in (401, 403)


def test_the_audit_page_shows_what_the_api_shows_and_is_linked_for_admins_only(daphne_server, world):
    users = get_user_model().objects
    browser = Client()
    browser.force_login(users.get(username="carol"))
    page = browser.get("/audit/", {"robot": "acme-1"})
    assert page.status_code == 200
    assert page.content.decode().count("<code>robot.start</code>") == 2
    assert b'href="/audit/"' in page.content
    assert b"/api/audit?robot=acme-1&amp;format=csv" in page.content
    assert b"since: " in browser.get("/audit/", {"since": "soon"}).content
    # Everyone administers their personal organization; acting in acme, where victor is a viewer, he has no link.
    browser.force_login(users.get(username="victor"))
    session = browser.session
    session[SESSION_ORGANIZATION] = world["acme"].id
    session.save()
    assert b'href="/audit/"' not in browser.get("/").content
    assert b"No entries." in browser.get("/audit/").content


def test_a_csv_cell_that_would_run_as_a_spreadsheet_formula_opens_as_text(daphne_server, world):
    services.record(
        "robot.update",
        door="rest",
        actor='=HYPERLINK("http://evil.example")',
        target="robot/acme-9",
        organization_id=world["acme"].id,
        organization_slug="acme",
    )
    with client(daphne_server, world["keys"]["carol"]) as http:
        exported = http.get("/api/audit", params={"format": "csv", "action": "robot.update"})
    rows = list(csv.DictReader(io.StringIO(exported.text)))
    assert [row["actor"] for row in rows] == ['\'=HYPERLINK("http://evil.example")']
    # The JSON export keeps the value as it was written.
    downloaded = read(daphne_server, world["keys"]["carol"], action="robot.update").json()["results"]
    assert [entry["actor"] for entry in downloaded] == ['=HYPERLINK("http://evil.example")']

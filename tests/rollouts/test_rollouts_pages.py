"""The dashboard's Rollouts pages as the server renders them: the picked organization, pages, counts, buttons by role.

tests/browser/test_dashboard_rollouts.py follows a rollout live in Chromium; these read the HTML only.
"""

from __future__ import annotations

import pytest
from django.db import connection
from django.test.utils import CaptureQueriesContext

from dashboard import services
from robots.services import create_robot
from rollouts.models import Rollout, RolloutRobot
from rollouts.services import create_release
from teams.models import Organization
from tests.rollouts.test_releases import config
from tests.teams.teamutil import team

pytestmark = pytest.mark.django_db


@pytest.fixture
def lab() -> Organization:
    lab = team("lab", dev="developer", boss="admin", op="operator", viewer="viewer")
    team("annex", dev="developer")
    return lab


def rollouts_of(organization: Organization, count: int, *, robots: int = 0) -> list[Rollout]:
    """Make finished rollouts of an organization, oldest first, each over `robots` robots (one failed)."""
    release = create_release(organization, config(), user=None)
    made = []
    for _ in range(count):
        rollout = Rollout.objects.create(
            organization=organization, release=release, selector="site=lab", state=Rollout.State.SUCCEEDED
        )
        for k in range(robots):
            robot, _ = create_robot(f"{organization.slug}-{rollout.id}-{k}", None, organization=organization)
            status = RolloutRobot.Status.FAILED if k == 0 else RolloutRobot.Status.SUCCEEDED
            RolloutRobot.objects.create(rollout=rollout, robot=robot, batch=0, status=status)
        made.append(rollout)
    return made


def login(client, lab: Organization, username: str):
    client.force_login(lab.memberships.get(user__username=username).user)
    return client


def test_the_list_shows_the_picked_organizations_rollouts_newest_first_with_their_robots_counted(client, lab):
    theirs = rollouts_of(lab, 2, robots=3)
    annex = rollouts_of(Organization.objects.get(slug="annex"), 1)
    dev = login(client, lab, "dev")
    page = dev.get("/rollouts/").content.decode()
    assert page.index(f'data-rollout="{annex[0].id}"') < page.index(f'data-rollout="{theirs[1].id}"')
    assert page.index(f'data-rollout="{theirs[1].id}"') < page.index(f'data-rollout="{theirs[0].id}"')
    assert '<span class="badge status-succeeded" data-status="succeeded">succeeded 2</span>' in page
    assert '<span class="badge status-failed" data-status="failed">failed 1</span>' in page
    dev.post("/organization", {"organization": "lab"})
    page = dev.get("/rollouts/").content.decode()
    assert f'data-rollout="{theirs[0].id}"' in page and f'data-rollout="{annex[0].id}"' not in page


def test_the_list_pages_by_id_and_costs_as_many_queries_for_many_rollouts_as_for_few(client, lab, monkeypatch):
    monkeypatch.setattr(services, "ROLLOUTS_PER_PAGE", 2)
    made = rollouts_of(lab, 3, robots=2)
    dev = login(client, lab, "dev")
    first = dev.get("/rollouts/").content.decode()
    assert f'href="?before={made[1].id}"' in first and f'data-rollout="{made[0].id}"' not in first
    older = dev.get(f"/rollouts/?before={made[1].id}").content.decode()
    assert f'data-rollout="{made[0].id}"' in older and 'id="rollouts-older"' not in older
    assert dev.get("/rollouts/?before=" + "9" * 40).status_code == 200
    monkeypatch.setattr(services, "ROLLOUTS_PER_PAGE", 100)
    with CaptureQueriesContext(connection) as few:
        dev.get("/rollouts/")
    rollouts_of(lab, 10, robots=1)
    with CaptureQueriesContext(connection) as many:
        dev.get("/rollouts/")
    assert len(few) == len(many)


@pytest.mark.parametrize(("username", "steers"), [("dev", True), ("boss", True), ("op", False), ("viewer", False)])
def test_only_a_developer_or_admin_is_shown_the_buttons_and_only_those_the_state_allows(client, lab, username, steers):
    (rollout,) = rollouts_of(lab, 1, robots=1)
    Rollout.objects.filter(pk=rollout.pk).update(state=Rollout.State.PAUSED)
    page = login(client, lab, username).get(f"/rollouts/{rollout.id}/").content.decode()
    assert ('data-steer="resume">' in page) is steers
    assert ('id="read-only"' in page) is not steers
    if steers:
        assert 'data-steer="pause" hidden>' in page and 'data-steer="abort">' in page


def test_a_missing_rollout_and_another_organizations_read_alike(client, lab):
    (rollout,) = rollouts_of(Organization.objects.get(slug="annex"), 1)
    viewer = login(client, lab, "viewer")
    theirs, missing = viewer.get(f"/rollouts/{rollout.id}/"), viewer.get(f"/rollouts/{rollout.id + 1}/")
    assert theirs.status_code == missing.status_code == 404
    assert theirs.content.replace(str(rollout.id).encode(), b"") == missing.content.replace(
        str(rollout.id + 1).encode(), b""
    )
    assert viewer.get("/rollouts/99999999999999999999/").status_code == 404, "past bigint: still a 404"

"""The dashboard's team pages refuse on the server what a role lacks, whatever the page showed."""

from __future__ import annotations

import pytest

from robots import access
from robots.models import ApiToken
from robots.services import issue_api_token
from teams.models import Membership

from .teamutil import robot_in, team, user

pytestmark = pytest.mark.django_db


@pytest.fixture
def lab():
    """A lab with an admin (ada) and a viewer (vic), and a robot."""
    organization = team("lab", ada="admin", vic="viewer")
    robot_in(organization, "lab-bot")
    return organization


def as_user(client, lab, username: str):
    """Log the test client in as a member of the lab."""
    client.force_login(lab.memberships.get(user__username=username).user)
    return client


def test_a_viewer_posting_the_admins_forms_is_refused_and_nothing_changes(client, lab):
    user("bob")
    viewer = as_user(client, lab, "vic")
    page = viewer.get("/organizations/lab/")
    assert page.status_code == 200
    assert b'id="member-form"' not in page.content
    assert viewer.post("/organizations/lab/", {"username": "bob", "role": "admin"}).status_code == 403
    assert viewer.post("/organizations/lab/members/ada", {"role": "viewer"}).status_code == 403
    assert viewer.post("/organizations/lab/members/ada", {"action": "remove"}).status_code == 403
    assert dict(lab.memberships.values_list("user__username", "role")) == {"ada": "admin", "vic": "viewer"}


def test_another_organizations_page_is_a_404_like_a_missing_one(client, lab):
    client.force_login(user("eve"))
    assert client.get("/organizations/lab/").status_code == 404
    assert client.get("/organizations/nothing/").status_code == 404


def test_the_picker_holds_the_session_to_a_member_organization_only(client, lab):
    admin = as_user(client, lab, "ada")
    assert admin.post("/organization", {"organization": "lab", "next": "/skills/"}).url == "/skills/"
    assert admin.session[access.SESSION_ORGANIZATION] == lab.id
    assert b'<option value="lab" selected>' in admin.get("/").content
    other = team("other", bob="admin")
    assert admin.post("/organization", {"organization": other.slug}).status_code == 404
    assert admin.session[access.SESSION_ORGANIZATION] == lab.id
    # An outside address is never followed.
    assert admin.post("/organization", {"organization": "", "next": "https://evil.example/"}).url == "/"
    assert access.SESSION_ORGANIZATION not in admin.session


def test_the_tokens_page_refuses_a_role_above_yours_and_a_foreign_revocation(client, lab):
    viewer = as_user(client, lab, "vic")
    refused = viewer.post("/tokens/", {"name": "x", "organization": "lab", "role": "operator"})
    assert refused.status_code == 400
    assert b"at most yours here (viewer)" in refused.content
    assert not ApiToken.objects.filter(name="x").exists()
    _, ada_token = issue_api_token(lab.memberships.get(user__username="ada").user, name="ada-ci", organization=lab)
    assert viewer.post(f"/tokens/{ada_token.pk}/revoke").status_code == 404
    assert ApiToken.objects.filter(pk=ada_token.pk).exists()
    made = viewer.post("/tokens/", {"name": "ro", "organization": "lab", "role": "viewer", "expires_in_days": "7"})
    assert made.url == "/tokens/"
    shown = viewer.get("/tokens/").content.decode()
    assert 'id="made-key"' in shown
    assert 'id="made-key"' not in viewer.get("/tokens/").content.decode()


def test_the_robot_page_gives_a_viewer_no_commands_and_an_admin_all(client, lab):
    viewer = as_user(client, lab, "vic").get("/robots/lab-bot/")
    assert viewer.context["rights"] == {"command": False, "develop": False, "administer": False}
    assert b"data-robot-command" not in viewer.content
    Membership.objects.filter(user__username="vic").update(role="developer")
    developer = client.get("/robots/lab-bot/")
    assert developer.context["rights"] == {"command": True, "develop": True, "administer": False}
    assert b"data-robot-command" in developer.content


def test_staff_keep_organizations_and_members_in_the_admin_and_others_never_reach_it(client, lab):
    client.force_login(lab.memberships.get(user__username="ada").user)
    assert client.get("/admin/teams/organization/").status_code == 302  # to the admin's login
    ops = user("ops")
    ops.is_staff = ops.is_superuser = True
    ops.save()
    client.force_login(ops)
    listing = client.get("/admin/teams/organization/?q=ada")
    assert listing.status_code == 200
    assert b"lab" in listing.content
    change = client.get(f"/admin/teams/organization/{lab.pk}/change/")
    assert change.status_code == 200
    assert b"memberships-0-role" in change.content
    robots = client.get(f"/admin/robots/robot/?organization__id__exact={lab.pk}")
    assert robots.status_code == 200
    assert b"lab-bot" in robots.content
    assert client.get("/admin/teams/membership/?role=viewer").status_code == 200

"""Organizations and members over the Robot API: who may see, add, change and remove, against the real daphne."""

from __future__ import annotations

import httpx
import pytest

from robots.models import ApiToken
from teams.models import Membership, Organization

from .teamutil import headers, login_token, team, user

pytestmark = pytest.mark.django_db(transaction=True)


def api(server, token: str) -> httpx.Client:
    """Return an HTTP client of the Robot API sending a token."""
    return httpx.Client(base_url=server.url + "/api", headers=headers(token), timeout=15)


def test_a_user_lists_their_personal_and_team_organizations_with_their_role(daphne_server):
    alice = user("alice")
    team("lab", alice="operator")
    team("other", bob="admin")
    with api(daphne_server, login_token(alice)) as http:
        rows = http.get("/organizations").json()
    assert rows == [
        {"slug": "alice", "name": "alice", "personal": True, "role": "admin"},
        {"slug": "lab", "name": "Lab", "personal": False, "role": "operator"},
    ]


def test_creating_an_organization_makes_its_creator_admin(daphne_server):
    alice = user("alice")
    with api(daphne_server, login_token(alice)) as http:
        made = http.post("/organizations", json={"slug": "vision-lab", "name": "Vision lab"})
        assert made.status_code == 201, made.text
        assert made.json() == {"slug": "vision-lab", "name": "Vision lab", "personal": False, "role": "admin"}
        assert http.get("/organizations/vision-lab/members").json()[0]["role"] == "admin"


@pytest.mark.parametrize(
    ("slug", "why"),
    [("Bad Slug", "lowercase"), ("alice", "taken"), ("bob", "taken"), ("-x", "lowercase")],
)
def test_a_bad_taken_or_another_users_slug_is_refused_and_nothing_is_made(daphne_server, slug, why):
    alice = user("alice")
    user("bob")  # bob's personal organization holds "bob"; his username would be taken anyway
    before = Organization.objects.count()
    with api(daphne_server, login_token(alice)) as http:
        answer = http.post("/organizations", json={"slug": slug})
    assert answer.status_code == 400
    assert why in answer.json()["slug"][0]
    assert Organization.objects.count() == before


def test_a_slug_that_is_another_users_name_is_refused_even_without_their_organization(daphne_server):
    alice = user("alice")
    carol = user("carol")
    Organization.objects.filter(personal_of=carol).update(slug="carol-own")
    with api(daphne_server, login_token(alice)) as http:
        answer = http.post("/organizations", json={"slug": "carol"})
    assert answer.status_code == 400
    assert answer.json() == {"slug": ["This slug is taken."]}


def test_another_organization_answers_exactly_like_a_missing_one(daphne_server):
    alice = user("alice")
    team("secret", bob="admin")
    with api(daphne_server, login_token(alice)) as http:
        for path in ("/organizations/{}", "/organizations/{}/members", "/organizations/{}/tokens"):
            other, missing = http.get(path.format("secret")), http.get(path.format("nothing"))
            assert other.status_code == missing.status_code == 404
            assert other.content == missing.content
        other = http.post("/organizations/secret/members", json={"username": "alice", "role": "admin"})
        missing = http.post("/organizations/nothing/members", json={"username": "alice", "role": "admin"})
        assert other.status_code == missing.status_code == 404
        assert other.content == missing.content
    assert not Membership.objects.filter(organization__slug="secret", user=alice).exists()


def test_a_viewer_reads_members_but_may_not_change_them(daphne_server):
    team("lab", admin="admin", vic="viewer")
    vic = user("vic2")
    Membership.objects.create(organization=Organization.objects.get(slug="lab"), user=vic, role="viewer")
    with api(daphne_server, login_token(vic)) as http:
        assert [m["username"] for m in http.get("/organizations/lab/members").json()] == ["admin", "vic", "vic2"]
        add = http.post("/organizations/lab/members", json={"username": "vic2", "role": "admin"})
        assert add.status_code == 403
        assert "admin role" in add.json()["detail"]
        assert "viewer" in add.json()["detail"]
        assert http.patch("/organizations/lab/members/vic", json={"role": "admin"}).status_code == 403
        assert http.delete("/organizations/lab/members/vic").status_code == 403
        assert http.get("/organizations/lab/tokens").status_code == 403
    assert Membership.objects.get(organization__slug="lab", user__username="vic").role == "viewer"


def test_an_admin_adds_changes_and_removes_members(daphne_server):
    lab = team("lab", ada="admin")
    user("bob")
    with api(daphne_server, login_token(lab.memberships.get().user)) as http:
        added = http.post("/organizations/lab/members", json={"username": "bob", "role": "viewer"})
        assert added.status_code == 201, added.text
        assert added.json()["role"] == "viewer"
        again = http.post("/organizations/lab/members", json={"username": "bob", "role": "viewer"})
        assert again.status_code == 400
        assert "Already a member" in again.json()["username"][0]
        nobody = http.post("/organizations/lab/members", json={"username": "nobody", "role": "viewer"})
        assert nobody.json() == {"username": ["No such user."]}
        bad = http.post("/organizations/lab/members", json={"username": "bob", "role": "king"})
        assert bad.status_code == 400
        assert "role" in bad.json()
        assert http.patch("/organizations/lab/members/bob", json={"role": "developer"}).json()["role"] == "developer"
        assert http.patch("/organizations/lab/members/nobody", json={"role": "viewer"}).status_code == 404
        assert http.delete("/organizations/lab/members/bob").status_code == 204
    assert list(lab.memberships.values_list("user__username", flat=True)) == ["ada"]


def test_an_organization_is_never_left_without_an_admin(daphne_server):
    lab = team("lab", ada="admin", bob="operator")
    with api(daphne_server, login_token(lab.memberships.get(role="admin").user)) as http:
        demoted = http.patch("/organizations/lab/members/ada", json={"role": "developer"})
        assert demoted.status_code == 400
        assert "at least one admin" in demoted.json()["role"][0]
        left = http.delete("/organizations/lab/members/ada")
        assert left.status_code == 400
        assert "at least one admin" in left.json()["role"][0]
        # With a second admin, the first may step down.
        assert http.patch("/organizations/lab/members/bob", json={"role": "admin"}).status_code == 200
        assert http.patch("/organizations/lab/members/ada", json={"role": "viewer"}).status_code == 200
    assert dict(lab.memberships.values_list("user__username", "role")) == {"ada": "viewer", "bob": "admin"}


def test_a_member_may_leave_but_not_with_a_scoped_token(daphne_server):
    lab = team("lab", ada="admin", bob="viewer")
    bob = lab.memberships.get(user__username="bob").user
    with api(daphne_server, login_token(bob)) as http:
        assert http.delete("/organizations/lab/members/ada").status_code == 403
        scoped = http.post("/tokens", json={"name": "ci", "organization": "lab", "role": "viewer"}).json()["key"]
    with api(daphne_server, scoped) as http:
        assert http.delete("/organizations/lab/members/bob").status_code == 403
    with api(daphne_server, login_token(bob)) as http:
        assert http.delete("/organizations/lab/members/bob").status_code == 204
    assert not lab.memberships.filter(user=bob).exists()
    # Leaving ended the token made for that organization.
    assert not ApiToken.objects.filter(user=bob, organization=lab).exists()

"""daphne serves the dashboard, the admin and the API over a real socket."""

from __future__ import annotations

import re

import httpx
import pytest
from django.contrib.auth import get_user_model

pytestmark = pytest.mark.django_db(transaction=True)


def login(client: httpx.Client, path: str, username: str, password: str) -> httpx.Response:
    """Log in through a Django login form the way a browser does."""
    form = client.get(path)
    assert form.status_code == 200
    csrf = re.search(r'name="csrfmiddlewaretoken" value="([^"]+)"', form.text).group(1)
    return client.post(
        path,
        data={"csrfmiddlewaretoken": csrf, "username": username, "password": password},
        headers={"Referer": str(form.url)},
        follow_redirects=True,
    )


def test_dashboard_sends_anonymous_visitors_to_login(daphne_server):
    response = httpx.get(daphne_server.url + "/", follow_redirects=False)
    assert response.status_code == 302
    assert response.headers["location"].startswith("/accounts/login/")


def test_operator_logs_in_and_sees_only_their_robots(daphne_server):
    from robots.services import create_robot

    User = get_user_model()
    alice = User.objects.create_user("alice", password="alice-pass-123")
    bob = User.objects.create_user("bob", password="bob-pass-123")
    create_robot("alice-bot", alice)
    create_robot("bob-bot", bob)

    with httpx.Client(base_url=daphne_server.url) as client:
        page = login(client, "/accounts/login/", "alice", "alice-pass-123")
        assert page.status_code == 200
        assert "alice-bot" in page.text
        assert "bob-bot" not in page.text


def test_admin_login_works_over_the_socket(daphne_server):
    get_user_model().objects.create_superuser("root-op", password="root-op-pass-123")
    with httpx.Client(base_url=daphne_server.url) as client:
        page = login(client, "/admin/login/?next=/admin/", "root-op", "root-op-pass-123")
        assert page.status_code == 200
        assert str(page.url).endswith("/admin/")
        assert "Site administration" in page.text
        assert "Robots" in page.text


def test_admin_rejects_a_wrong_password(daphne_server):
    get_user_model().objects.create_superuser("root-op", password="root-op-pass-123")
    with httpx.Client(base_url=daphne_server.url) as client:
        page = login(client, "/admin/login/?next=/admin/", "root-op", "wrong")
        assert "Please enter the correct username and password" in page.text


def test_health_reports_database_and_redis(daphne_server):
    response = httpx.get(daphne_server.url + "/api/health")
    assert response.status_code == 200
    assert response.json() == {"status": "ok", "database": True, "redis": True}


def test_openapi_schema_and_docs_are_served(daphne_server):
    schema = httpx.get(daphne_server.url + "/api/schema/?format=json")
    assert schema.status_code == 200
    assert schema.json()["info"]["title"] == "bridgeOS Cloud Robot API"
    docs = httpx.get(daphne_server.url + "/api/docs/")
    assert docs.status_code == 200
    # The Swagger UI assets are served locally, not from a CDN this machine cannot reach.
    assert "cdn.jsdelivr" not in docs.text


def test_static_files_are_served(daphne_server):
    response = httpx.get(daphne_server.url + "/static/css/bridgeos.css")
    assert response.status_code == 200
    assert "text/css" in response.headers["content-type"]

"""The admin's pages name the dashboard's icon, so a browser does not ask for a /favicon.ico nothing serves."""

from __future__ import annotations

import re

import pytest
from django.conf import settings
from django.contrib.auth import get_user_model
from django.test import Client

from tests.teams.teamutil import robot_in, team

pytestmark = pytest.mark.django_db

ICON = re.compile(rb'<link rel="icon" href="([^"]+)" type="image/svg\+xml">')


def test_every_kind_of_admin_page_names_the_dashboards_icon_and_keeps_its_own_title():
    robot_in(team("lab", ada="admin"), "lab-1")
    client = Client()
    login = client.get("/admin/login/")
    ops = get_user_model().objects.create_user("ops", is_staff=True, is_superuser=True)
    client.force_login(ops)
    pages = [login] + [
        client.get(url) for url in ("/admin/", "/admin/robots/robot/", "/admin/robots/robot/lab-1/change/")
    ]
    for page in pages:
        assert page.status_code == 200
        assert ICON.findall(page.content) == [f"{settings.STATIC_URL}img/bridgeos.svg".encode()]
        assert b"bridgeOS Cloud administration" in page.content
        assert b"<title>" in page.content and b"| bridgeOS Cloud</title>" in page.content
    # The change form adds its own scripts to the head after the icon, as Django's does.
    assert b"jsi18n" in pages[-1].content
    assert (settings.BASE_DIR / "static" / "img" / "bridgeos.svg").is_file()

"""Large answers are gzipped for clients that accept it; small ones and other clients get plain JSON."""

from __future__ import annotations

import gzip
import json

import pytest
from django.contrib.auth import get_user_model
from rest_framework.test import APIClient

from .apiutil import robot_of

pytestmark = pytest.mark.django_db


@pytest.fixture
def api() -> APIClient:
    owner = get_user_model().objects.create_user("big-fleet")
    for n in range(30):
        robot_of(owner, f"bot-{n:02d}")
    client = APIClient()
    client.force_authenticate(owner)
    return client


def test_the_fleet_is_gzipped_for_a_client_that_accepts_it(api):
    plain = api.get("/api/robot")
    assert "Content-Encoding" not in plain
    assert len(plain.content) > 32 * 1024
    packed = api.get("/api/robot", HTTP_ACCEPT_ENCODING="gzip, deflate")
    assert packed["Content-Encoding"] == "gzip"
    assert "Accept-Encoding" in packed["Vary"]
    assert int(packed["Content-Length"]) == len(packed.content) < len(plain.content) / 5
    assert json.loads(gzip.decompress(packed.content)) == plain.json()


def test_a_small_answer_is_not_compressed(api):
    response = api.get("/api/robot/bot-00/info", HTTP_ACCEPT_ENCODING="gzip")
    assert "Content-Encoding" not in response
    assert response.json()["id"] == "bot-00"

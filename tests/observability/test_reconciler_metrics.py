"""The reconciler's actions, counted after a real round against the process runtime."""

from __future__ import annotations

import pytest
from django.contrib.auth import get_user_model

from bridgeos_agent.skillconfig import load_sample_skill_config
from monitoring.prometheus import exposition
from robots.services import create_robot
from skills.cloud.reconcile import reconcile
from skills.models import CloudInstance, Component
from skills.services import add_skill

from .promutil import value

pytestmark = [pytest.mark.django_db(transaction=True)]


def test_a_cloud_copy_whose_process_is_gone_is_counted_as_crashed(settings):
    settings.BRIDGEOS = {**settings.BRIDGEOS, "CLOUD_RUNTIME": "process"}
    owner = get_user_model().objects.create_user("copy-owner")
    robot, _ = create_robot("copy-bot", owner)
    add_skill(robot, load_sample_skill_config().model_dump(mode="json"))
    component = Component.objects.filter(skill__robot=robot, location="either").first()
    # The row says the copy runs; no process of it does (it died while nobody watched).
    CloudInstance.objects.create(component=component, desired="running", status="running", runtime="process")
    before = exposition().decode()

    done = reconcile()

    after = exposition().decode()
    assert done["crashed"] == 1
    grown = value(after, "bridgeos_reconciler_actions_total", action="crashed") - value(
        before, "bridgeos_reconciler_actions_total", action="crashed"
    )
    assert grown == 1
    # The copy now waits for its restart: the state gauge says so at the next scrape.
    assert value(after, "bridgeos_cloud_copies", state="starting") >= 1

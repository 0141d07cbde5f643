"""`cloud_down` leaves no cloud copy behind, even with the reconciler and a start at work meanwhile.

`make run`'s stop once left a Swarm service made 20 s after it began: the reconciler took each copy
the sweep removed for a crash and started it again, and a start in flight recorded its copy
running. Real PostgreSQL and the process runtime; the reconciler's rounds and the stop landing
are put where the race put them.
"""

from __future__ import annotations

import asyncio
import io

import pytest
from asgiref.sync import sync_to_async
from django.contrib.auth import get_user_model
from django.core.management import call_command

from bridgeos_agent.protocol import ComponentStatusName as CS
from robots.services import create_robot
from skills.cloud import converge as converge_module
from skills.cloud.converge import converge
from skills.cloud.orchestration import with_runtime
from skills.cloud.process import CloudProcessRuntime
from skills.cloud.reconcile import reconcile
from skills.cloud.runtime import KIND_COMPONENT
from skills.models import CloudInstance, Component
from skills.services import add_skill
from tests.agent.conftest import skill_config
from tests.conftest import remove_cloud_copies

pytestmark = [pytest.mark.django_db(transaction=True), pytest.mark.timeout(90)]


@pytest.fixture
def instance(settings):
    """A cloud copy's row that wants it running, on the process runtime; whatever runs is removed after."""
    settings.BRIDGEOS = {**settings.BRIDGEOS, "CLOUD_RUNTIME": "process"}
    robot, _ = create_robot("down-bot", get_user_model().objects.create_user("down-owner"))
    add_skill(robot, skill_config(location="cloud", count=1))
    component = Component.objects.get(skill__robot=robot)
    row = CloudInstance.objects.create(
        component=component, desired="running", status=CS.PENDING, runtime="process", token="t1"
    )
    yield row
    remove_cloud_copies("process")


def copies() -> int:
    """How many cloud copies run."""
    return len(
        [item for item in with_runtime("test", lambda runtime: runtime.observe()) if item.kind == KIND_COMPONENT]
    )


def test_the_reconciler_at_work_during_the_sweep_starts_nothing_again(instance, monkeypatch):
    assert converge(instance.pk, "t1") == "running"
    assert copies() == 1
    remove = CloudProcessRuntime.remove

    async def remove_while_the_reconciler_works(self, item):
        await remove(self, item)
        # Two beats while the sweep waits for its other copies to stop: the first sees this one
        # gone, the second is past the first restart's delay.
        await sync_to_async(reconcile)()
        await asyncio.sleep(1.2)
        await sync_to_async(reconcile)()

    monkeypatch.setattr(CloudProcessRuntime, "remove", remove_while_the_reconciler_works)
    call_command("cloud_down", stdout=io.StringIO())
    monkeypatch.undo()

    assert copies() == 0  # before the fix: the reconciler's restart ran on
    instance.refresh_from_db()
    assert (instance.desired, instance.status) == ("stopped", CS.STOPPED)


def test_a_start_in_flight_when_cloud_down_lands_removes_its_copy(instance, monkeypatch):
    launch = converge_module.with_runtime

    def launch_then_cloud_down_lands(robot_id, operation, **kwargs):
        answer = launch(robot_id, operation, **kwargs)
        # The copy runs and its start is about to be recorded: cloud_down marks it unwanted now.
        CloudInstance.objects.filter(pk=instance.pk).update(desired="stopped")
        return answer

    monkeypatch.setattr(converge_module, "with_runtime", launch_then_cloud_down_lands)
    outcome = converge(instance.pk, "t1")
    monkeypatch.undo()

    assert outcome == "stopped"  # before the fix: "running", recorded, and the process ran on
    assert copies() == 0
    instance.refresh_from_db()
    assert instance.status == CS.STOPPED
    assert Component.objects.get(pk=instance.component_id).status != CS.RUNNING

"""A worker's report about a robot that is being deleted, or was deleted since its task began.

CI found a discovery server's task reporting "running" for a robot deleted meanwhile: its event
failed the foreign key at commit, an ERROR in the worker's log. Real PostgreSQL, two connections.
"""

from __future__ import annotations

import threading
import time

import pytest
from django.db import close_old_connections, connection, transaction

from bridgeos_agent.protocol import ComponentStatusName as CS
from monitoring.models import Event
from robots.models import Robot
from robots.services import create_robot, delete_robot
from skills.cloud.perrobot import report
from skills.models import RobotCloud

pytestmark = [pytest.mark.django_db(transaction=True), pytest.mark.timeout(60)]

PORT = 11811


def cloud_of(robot_id: str) -> RobotCloud:
    """Give the robot a discovery server's row, as a ROS 2 robot's login does, and return it."""
    from django.contrib.auth import get_user_model

    create_robot(robot_id, get_user_model().objects.create_user(f"owner-{robot_id}"))
    return RobotCloud.objects.create(robot_id=robot_id, ros2_discovery_port=PORT, ros2_discovery_status=CS.PENDING)


def report_running(cloud: RobotCloud) -> None:
    report(
        cloud,
        "ros2_discovery_status",
        CS.RUNNING,
        "",
        robot_id=cloud.robot_id,
        text=f"ROS 2 discovery server of robot {cloud.robot_id}",
        kind="cloud_ros2_discovery",
    )


def in_thread(work, name: str) -> tuple[threading.Thread, list[BaseException]]:
    """Run ``work`` on a connection of its own; return the thread and the errors it raised."""
    errors: list[BaseException] = []

    def run() -> None:
        try:
            work()
        except BaseException as exc:  # handed to the test, which asserts there were none
            errors.append(exc)
        finally:
            connection.close()

    thread = threading.Thread(target=run, name=name)
    thread.start()
    return thread, errors


def test_a_report_about_a_robot_deleted_since_its_row_was_read_writes_nothing():
    cloud = cloud_of("gone-1")
    delete_robot(Robot.objects.get(pk="gone-1"))

    report_running(cloud)  # before the fix: IntegrityError at commit (the event's robot is gone)

    assert not Event.objects.filter(robot_id="gone-1").exists()
    assert not RobotCloud.objects.filter(robot_id="gone-1").exists()


def test_a_report_waits_for_a_deletion_under_way_and_then_writes_nothing():
    cloud = cloud_of("gone-2")
    locked = threading.Event()

    def deletion() -> None:
        # delete_robot's order: the robot's row first, then its dependents; held a second here.
        with transaction.atomic():
            robot = Robot.objects.select_for_update().get(pk="gone-2")
            locked.set()
            time.sleep(1.0)
            robot.delete()

    thread, errors = in_thread(deletion, "deletion")
    assert locked.wait(10)
    started = time.monotonic()
    report_running(cloud)  # before the fix: a deadlock, or the event's foreign key failing at commit
    waited = time.monotonic() - started
    thread.join(20)

    assert errors == []
    assert waited >= 0.5, "the report did not wait for the deletion holding the robot"
    assert not Robot.objects.filter(pk="gone-2").exists()
    assert not Event.objects.filter(robot_id="gone-2").exists()


def test_a_deletion_waits_for_a_report_under_way_and_takes_its_event_with_the_robot():
    cloud = cloud_of("gone-3")
    with transaction.atomic():
        report_running(cloud)
        assert Event.objects.filter(robot_id="gone-3", kind="cloud_ros2_discovery").count() == 1
        thread, errors = in_thread(lambda: delete_robot(Robot.objects.get(pk="gone-3")), "deletion")
        time.sleep(1.0)
        assert thread.is_alive(), "the deletion did not wait for the report's transaction"
    thread.join(20)
    close_old_connections()

    assert errors == []
    assert not Robot.objects.filter(pk="gone-3").exists()
    assert not Event.objects.filter(robot_id="gone-3").exists()

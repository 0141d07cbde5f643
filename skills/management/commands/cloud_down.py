"""Remove everything this cloud runs on its engine: cloud copies, ROS masters, ROS 2 discovery servers, networks."""

from __future__ import annotations

import asyncio
from typing import Any

from django.core.management.base import BaseCommand
from django.db import transaction

from skills.cloud.orchestration import STOPPED, with_runtime
from skills.cloud.relay import stop_all_relays
from skills.cloud.runtime import CloudRuntime, cloud_id, runtime_name
from skills.models import CloudInstance, Component, RobotCloud


class Command(BaseCommand):
    help = (
        "Stop every cloud copy, ROS master and ROS 2 discovery server of this cloud and remove its networks"
        " (`make run` does on exit)."
    )

    def handle(self, *args: Any, **options: Any) -> None:
        async def sweep(runtime: CloudRuntime) -> tuple[int, int]:
            found = await runtime.observe()
            # Side by side: each removal waits for its containers to stop, up to their grace period.
            await asyncio.gather(*(runtime.remove(item) for item in found))
            networks = await runtime.networks()
            for name in networks.values():
                await runtime.remove_network_named(name)
            return len(found), len(networks)

        # No longer wanted first: otherwise the reconciler takes each copy the sweep removes for a
        # crash and starts it again, and a start in flight records it running (both outlived make run).
        CloudInstance.objects.exclude(desired=STOPPED).update(desired=STOPPED)
        removed, networks = with_runtime("cloud-down", sweep)
        removed += stop_all_relays()  # processes whatever the runtime
        with transaction.atomic():
            CloudInstance.objects.exclude(status="stopped").update(desired=STOPPED, status="stopped", container={})
            Component.objects.filter(active_location="cloud").update(status="stopped")
            RobotCloud.objects.exclude(ros_master_status="stopped").update(ros_master_status="stopped")
            RobotCloud.objects.exclude(ros2_discovery_status="stopped").update(ros2_discovery_status="stopped")
        self.stdout.write(
            f"cloud {cloud_id()} ({runtime_name()}): removed {removed} copies, ROS masters and discovery servers,"
            f" {networks} networks"
        )

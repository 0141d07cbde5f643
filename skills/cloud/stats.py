"""Turn the resource usage of the running cloud copies into metrics."""

from __future__ import annotations

import asyncio
import concurrent.futures
import logging
import time

from bridgeos_agent.protocol import Event, MetricPoint
from bridgeos_agent.runtime.base import RuntimeFailure
from monitoring.ingest import MetricWriter
from monitoring.live import LiveFeed
from robots.services import push_to_robot

from .backends import create_cloud_runtime

logger = logging.getLogger(__name__)

# --------------------------------------------------------------------------- stats


def collect_stats(robot_ids: set[str]) -> int:
    """Measure the running cloud copies of these robots; store, broadcast and send the figures."""
    if not robot_ids:
        return 0

    async def measure_all() -> dict[str, list[MetricPoint]]:
        async def one(robot_id: str) -> tuple[str, list[MetricPoint]]:
            runtime = create_cloud_runtime(robot_id)
            try:
                usages = await runtime.stats()
            except RuntimeFailure:
                return robot_id, []
            finally:
                await runtime.close()
            ts = time.time()
            labels = {"location": "cloud"}
            points = []
            for (skill_id, component_id), usage in usages.items():
                for name, value in (("cpu", round(100 * usage.cpu, 2)), ("ram", round(usage.ram, 1))):
                    point = MetricPoint(
                        name=name, value=float(value), ts=ts, skill=skill_id, component=component_id, labels=labels
                    )
                    points.append(point)
            return robot_id, points

        measured = dict(await asyncio.gather(*(one(robot_id) for robot_id in sorted(robot_ids))))
        measured = {robot_id: points for robot_id, points in measured.items() if points}
        if measured:
            # The ingest the robots' metrics go through: COPY in one batch, then the live feed.
            writer = MetricWriter()
            writer.start()
            for robot_id, points in measured.items():
                writer.add(robot_id, points)
            await writer.close()
            # Once the rows are committed: clients never hear of points that were not stored.
            feed = LiveFeed()
            for robot_id, points in measured.items():
                feed.add_metrics(robot_id, points)
            await feed.close()
        return measured

    try:
        asyncio.get_running_loop()
        running = True
    except RuntimeError:
        running = False
    if running:
        with concurrent.futures.ThreadPoolExecutor(1) as pool:
            measured = pool.submit(asyncio.run, measure_all()).result()
    else:
        measured = asyncio.run(measure_all())
    for robot_id, points in measured.items():
        push_to_robot(robot_id, Event.METRICS, {"metrics": points})
    return sum(len(points) for points in measured.values())

"""The fault suite's rig: private clouds, stores, real agents and robot links to break, and what they stored.

    base    where the suite's database and Redis are, wait_until, kill_group, scratch dirs
    cloud   a private cloud: its env and database, daphne (CloudServer), Worker, Beat, robots in it
    stores  a redis-server and a PostgreSQL cluster of a scenario's own, and the points they hold
    fleet   one real agent (Agent) or many in one process (Fleet), and the components they start
    state   a digest of every table of a cloud served from this process (snapshot, changed)
    net     a robot's network namespace and the veth link to it (RobotLink)

`python -m benchmarks.chaos.rig` is the rig's own command, run in child processes (see __main__).
"""

from __future__ import annotations

from benchmarks.chaos.rig.base import (
    BIN,
    scratch_dir,
    tail,
    wait_until,
)
from benchmarks.chaos.rig.cloud import (
    Beat,
    Cloud,
    CloudServer,
    Worker,
    api_token,
    create_robots,
    shared_cloud_env,
    start_daphne,
)
from benchmarks.chaos.rig.fleet import Agent, Fleet, instances, kill_instances, settled_points
from benchmarks.chaos.rig.net import RobotLink
from benchmarks.chaos.rig.state import changed, snapshot
from benchmarks.chaos.rig.stores import PrivatePostgres, PrivateRedis, StoredPoints, count_stored

__all__ = [
    "BIN",
    "Agent",
    "Beat",
    "Cloud",
    "CloudServer",
    "Fleet",
    "PrivatePostgres",
    "PrivateRedis",
    "RobotLink",
    "StoredPoints",
    "Worker",
    "api_token",
    "changed",
    "count_stored",
    "create_robots",
    "instances",
    "kill_instances",
    "scratch_dir",
    "settled_points",
    "shared_cloud_env",
    "snapshot",
    "start_daphne",
    "tail",
    "wait_until",
]

"""Scenario 7, hostile input: fuzzed frames on every door, schemathesis on every API route, cross-tenant access.

Against a real daphne: (a) thousands of fuzzed frames per WebSocket door (malformed JSON, wrong types,
huge frames, binary junk, valid-looking envelopes with wrong fields, frames before authentication,
replayed ids), counting server errors (`internal_error` answers, closes with 1011, tracebacks in
daphne's log) and proving no table changed; (b) schemathesis over every operation of the published
OpenAPI schema, 0 server errors and no change from a refused request; (c) a robot token acting as
another robot and a user reaching another user's robot through every door the URL resolver and the
WebSocket routing list, all refused; and a viewer of the robot's own organization on every door that
needs more than reading, all refused while her reads are answered.
"""

from __future__ import annotations

import logging

from benchmarks.chaos import Outcome
from benchmarks.chaos.hostile.fuzz import fuzz_outcomes, websocket_routes
from benchmarks.chaos.hostile.rules import published_robot_routes
from benchmarks.chaos.hostile.schema import schemathesis_outcome
from benchmarks.chaos.hostile.tenancy import Tenancy, cross_role, cross_tenant, cross_tenant_outcome
from benchmarks.chaos.hostile.world import NAME, RecordingRobot, make_world
from benchmarks.chaos.rig import shared_cloud_env as cloud_env
from benchmarks.chaos.rig import start_daphne

__all__ = [
    "INJECTS",
    "LIMITS_OFF",
    "NAME",
    "RecordingRobot",
    "Tenancy",
    "cloud_env",
    "cross_role",
    "cross_tenant",
    "make_world",
    "published_robot_routes",
    "run",
    "start_daphne",
    "websocket_routes",
]

INJECTS = "hostile input: fuzzed frames on every WebSocket door, schemathesis on every API route, cross-tenant access"
# Lifted so the fuzzer reaches the handlers, not the rate and brute-force limits in front of them.
LIMITS_OFF = {
    "BRIDGEOS_ROBOT_FRAMES_PER_S": "1000000",
    "BRIDGEOS_ROBOT_FRAME_BURST": "1000000",
    "BRIDGEOS_CLIENT_FRAMES_PER_S": "1000000",
    "BRIDGEOS_CLIENT_FRAME_BURST": "1000000",
    "BRIDGEOS_AUTH_FAILURES": "100000000",
    "BRIDGEOS_AUTH_FAILURES_PER_ADDRESS": "100000000",
}


def run(quick: bool) -> list[Outcome]:
    """Play the three parts against one daphne of the scenario's own."""
    logging.getLogger("httpx").setLevel(logging.WARNING)  # a line per request would drown the table
    env = cloud_env()
    daphne = start_daphne(env, NAME, LIMITS_OFF)
    try:
        world = make_world(f"http://127.0.0.1:{daphne.port}", daphne.ws_url)
        outcomes = [cross_tenant_outcome(world)]
        outcomes += fuzz_outcomes(world, daphne, 1_000 if quick else 10_000)
        outcomes.append(schemathesis_outcome(world, daphne, 3 if quick else 50))
        return outcomes
    finally:
        daphne.stop()

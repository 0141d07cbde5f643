"""Scenario 7 in its short form: fuzzed frames, schemathesis and cross-tenant attempts break nothing and reach no one."""

from __future__ import annotations

import importlib
import time

import pytest

from benchmarks.chaos import summary

pytestmark = pytest.mark.django_db(transaction=True)

hostile = importlib.import_module("benchmarks.chaos.hostile")


@pytest.mark.timeout(240)
# The hostile clients' own library (websockets' sync client) logs a stream that the server ended
# mid-frame, on purpose, after a huge or junk frame, as an internal error of its own.
@pytest.mark.log_errors(r"websockets\.client: unexpected internal error[\s\S]*EOFError: stream ended")
def test_hostile_input_breaks_nothing_and_reaches_no_other_tenant():
    outcomes = hostile.run(quick=True)

    failed = [f"{o.injected}: {o.detail}" for o in outcomes if not o.passed]
    assert not failed, failed
    figures = summary(outcomes)
    doors = hostile.websocket_routes()
    assert {"ws/robot/", "ws/client/"} <= set(doors)
    assert figures["fuzz_frames"] == 1_000 * len(doors)
    assert figures["fuzz_server_errors"] == 0
    # Two callers (Bob's API token and bob-bot's robot token) on each published robot route, and more doors besides.
    assert figures["cross_tenant_attempts"] > 2 * len(hostile.published_robot_routes())
    assert figures["cross_tenant_allowed"] == 0
    # A viewer of Alice's organization, on every door of alice-bot that needs more than reading.
    assert figures["cross_role_attempts"] > len(hostile.published_robot_routes())
    assert figures["cross_role_allowed"] == 0
    assert any(o.injected.startswith("schemathesis over") and o.sent > 0 for o in outcomes)


@pytest.mark.timeout(120)
def test_the_cross_tenant_tally_counts_an_access_that_is_granted():
    # Staff may see every robot: played as the intruder, its REST calls on alice-bot must count as allowed.
    env = hostile.cloud_env()
    daphne = hostile.start_daphne(env, "hostile-control", hostile.LIMITS_OFF)
    try:
        world = hostile.make_world(f"http://127.0.0.1:{daphne.port}", daphne.ws_url)
        alice_robot = hostile.RecordingRobot(world.ws, "alice-bot", world.robot_tokens["alice-bot"])
        time.sleep(0.5)
        try:
            tally, unclassified = hostile.cross_tenant(world, alice_robot, intruder="ops")
        finally:
            alice_robot.close()
    finally:
        daphne.stop()
    assert not unclassified
    granted = [hole for hole in tally.holes if "/api/robot/alice-bot" in hole]
    assert len(granted) >= len(hostile.published_robot_routes()), tally.holes
    # A command staff may send reaches alice-bot's socket, and the tally sees it arrive there.
    assert any("reached=[{" in hole for hole in granted), granted


@pytest.mark.timeout(120)
def test_the_cross_role_tally_counts_an_access_that_is_granted():
    # Otto is an operator of Alice's organization: played as the viewer, his commands must count as allowed.
    env = hostile.cloud_env()
    daphne = hostile.start_daphne(env, "hostile-role-control", hostile.LIMITS_OFF)
    try:
        world = hostile.make_world(f"http://127.0.0.1:{daphne.port}", daphne.ws_url)
        alice_robot = hostile.RecordingRobot(world.ws, "alice-bot", world.robot_tokens["alice-bot"])
        time.sleep(0.5)
        try:
            tally = hostile.Tenancy()
            hostile.cross_role(world, alice_robot, tally, member="otto")
        finally:
            alice_robot.close()
    finally:
        daphne.stop()
    assert tally.attempts == 0
    assert not tally.reads_refused, tally.reads_refused
    # Commands on the REST routes, the fleet's and the client socket reach alice-bot, and the tally sees them there.
    assert any("/api/robot/alice-bot/start as otto" in hole and "reached=[{" in hole for hole in tally.holes)
    assert any(hole.startswith("robot_start for alice-bot as otto") for hole in tally.holes), tally.holes
    assert any(hole.startswith("POST /api/robot/start as otto") for hole in tally.holes), tally.holes
    assert any(hole.startswith("WS /ws/foxglove/") and "as otto: opened" in hole for hole in tally.holes), tally.holes
    # What an admin alone may do stays refused, so the figure is neither all nor nothing.
    assert 0 < tally.role_allowed < tally.role_attempts, tally.holes
    admins_only = ("DELETE /api/robot/alice-bot ", "POST /api/robot/alice-bot/token ", "GET /api/robot/alice-bot/vpn ")
    assert not any(hole.startswith((*admins_only, "robot_config_update")) for hole in tally.holes), tally.holes

"""A robot's link cut, then restored: takeover (Algorithm 7) in time, revert without duplicates, backlog in order.

The real agent (`--simulate`, process runtime) runs in a network namespace of its own, joined to
this machine by one veth pair; the cloud (daphne + a Celery worker launching cloud copies as
processes) listens on this machine's end. The Skill's three components run in the cloud
(offloading "cloud"). Then the robot's end of the link goes down: no packet passes and no
socket is told. Measured: the time from the cut until the robot runs its own copy of every
cloud component (takeover, must be <= connection_lost_after + 2 s), the running instances of
each component once the link is back and the robot has handed the role back (must be exactly
one: 0 duplicates), and the metric points the agent buffered during the cut: delivered with 0
lost, 0 duplicated (the agent's own count of points sent against the rows stored), and in order
(the stored arrival order of the robot's series follows the points' time).
"""

from __future__ import annotations

import time

from benchmarks._common import log
from benchmarks.chaos import Outcome
from benchmarks.chaos.rig import (
    Agent,
    Cloud,
    RobotLink,
    instances,
    kill_instances,
    settled_points,
    tail,
    wait_until,
)

NAME = "link"
INJECTS = "robot link cut (veth down in its namespace), then restored"

ROBOT = "chaos-link"
SKILL = "relay"
COMPONENTS = ("stage-0", "stage-1", "stage-2")
SAMPLE_S = 0.5


def skill() -> dict:
    """Three movable components that just run, launchable on the robot and in the cloud as processes."""
    spec = {"command": ["sleep", "3600"]}
    return {
        "skill": "Relay",
        "skill_id": SKILL,
        "components": {
            name: {
                "name": name,
                "location": "either",
                "ros": False,
                "resources": {"cpu": 0.05, "ram": 16},
                "robot": spec,
                "cloud": spec,
            }
            for name in COMPONENTS
        },
    }


def run(quick: bool) -> list[Outcome]:
    """Cut the robot's link (10 s quick, 5 min full), restore it, and report what survived."""
    lost_after = 3.0 if quick else 15.0
    heartbeat = 0.5 if quick else 5.0
    cut_s = 10.0 if quick else 300.0
    outcome = Outcome(scenario=NAME, injected=f"link cut {cut_s:g} s")
    link = RobotLink()
    cloud = Cloud(NAME, host=link.cloud_address, celery=True)
    agent: Agent | None = None
    kill_instances(ROBOT, SKILL)  # a killed earlier run's cloud copies
    try:
        cloud.start()
        config = {"offloading": "cloud", "heartbeat_interval": heartbeat, "connection_lost_after": lost_after}
        token, api_token = cloud.add_robot(ROBOT, config=config, skills=[skill()])
        cloud.wait_celery()
        agent = Agent(
            ROBOT,
            token,
            cloud.server.ws_url,
            cloud.dir / "agent",
            cloud.dir / "agent.log",
            namespace=link.namespace,
            sample_interval=SAMPLE_S,
        )
        wait_until(lambda: (agent.try_scrape() or {}).get("bridgeos_agent_link_up") == 1, "the agent connected", 60)
        response = cloud.api(api_token, "POST", f"/api/robot/{ROBOT}/skill/{SKILL}/start", params={"wait": 20})
        if response.status_code != 200:
            raise RuntimeError(f"starting the Skill: {response.status_code} {response.text[:500]}")

        def placed_in_cloud() -> bool:
            running = instances(ROBOT, SKILL)
            return all(running[(c, "cloud")] == 1 and running[(c, "robot")] == 0 for c in COMPONENTS)

        wait_until(placed_in_cloud, "the cloud copies running and none on the robot", 60)
        time.sleep(2 * SAMPLE_S)
        before = agent.scrape()
        log(f"link: cutting for {cut_s:g} s (connection_lost_after {lost_after:g} s)")
        cut_at = time.monotonic()
        link.cut()

        def taken_over() -> bool:
            running = instances(ROBOT, SKILL)
            return all(running[(c, "robot")] >= 1 for c in COMPONENTS)

        wait_until(taken_over, "the takeover", lost_after + 30, interval=0.05)
        takeover_s = time.monotonic() - cut_at
        log(f"link: takeover {takeover_s:.2f} s after the cut")
        time.sleep(max(0.0, cut_at + cut_s - time.monotonic()))
        during = agent.scrape()
        link.restore()
        restored_at = time.monotonic()

        def reconnected() -> bool:
            return (agent.try_scrape() or {}).get("bridgeos_agent_link_up") == 1

        wait_until(reconnected, "the agent reconnected", 60, interval=0.05)
        reconnect_s = time.monotonic() - restored_at

        def reverted() -> bool:
            running = instances(ROBOT, SKILL)
            stats = agent.try_scrape() or {}
            return (
                all(running[(c, "robot")] == 0 for c in COMPONENTS)
                and stats.get("bridgeos_agent_link_up") == 1
                and stats.get("bridgeos_agent_outbox_frames") == 0
            )

        wait_until(reverted, "the revert and the backlog delivered", 90, interval=0.05)
        recover_s = time.monotonic() - restored_at
        time.sleep(1.0)  # a late duplicate would show now
        running = instances(ROBOT, SKILL)
        duplicates = sum(max(0, running[(c, "robot")] + running[(c, "cloud")] - 1) for c in COMPONENTS)
        missing = [c for c in COMPONENTS if running[(c, "robot")] + running[(c, "cloud")] == 0]
        after, stored, duplicated = settled_points(agent, cloud, ROBOT)
        sent = int(after.get("bridgeos_agent_metric_points_sent_total", 0))
        # Every point sent by `after` is stored: nothing was owed, so each was acked after its COPY.
        lost = max(0, sent - (stored - duplicated))
        backlog_points = int(
            during.get("bridgeos_agent_metric_points_sent_total", 0)
            - before.get("bridgeos_agent_metric_points_sent_total", 0)
        )
        disorder = cloud.out_of_order(ROBOT)
        outcome.sent, outcome.stored, outcome.lost, outcome.duplicated = sent, stored, lost, duplicated
        outcome.recover_s = round(recover_s, 2)
        outcome.figures = {
            "takeover_s": round(takeover_s, 2),
            "connection_lost_after_s": lost_after,
            "cut_s": cut_s,
            "reconnect_after_restore_s": round(reconnect_s, 2),
            "backlog_points": backlog_points,
            "backlog_frames": int(during.get("bridgeos_agent_outbox_frames", 0)),
            "duplicate_components": duplicates,
            "missing_components": len(missing),
            "out_of_order": disorder,
        }
        checks = {
            f"takeover {takeover_s:.2f} s > {lost_after + 2:g} s": takeover_s <= lost_after + 2,
            f"{duplicates} duplicate component(s) {dict(running)}": duplicates == 0,
            f"components running nowhere: {missing}": not missing,
            f"{lost} point(s) lost": lost == 0,
            f"{duplicated} point(s) duplicated": duplicated == 0,
            f"{disorder} point(s) out of order": disorder == 0,
            "no backlog was buffered": backlog_points > 0,
            "the agent died": agent.alive(),
        }
        failed = [what for what, ok in checks.items() if not ok]
        outcome.passed = not failed
        outcome.detail = "; ".join(failed) or (
            f"takeover {takeover_s:.2f} s, {backlog_points} points buffered and delivered in order"
        )
    except Exception as exc:
        outcome.detail = f"{exc}\n{tail(cloud.dir / 'agent.log')}"
        raise
    finally:
        if agent is not None:
            agent.stop()
        cloud.stop()
        link.close()
        kill_instances(ROBOT, SKILL)
    return [outcome]

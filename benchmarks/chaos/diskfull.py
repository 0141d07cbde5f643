"""The robot's disk fills under the outbox: the agent runs on, says so, and loses no state event.

The real agent (`--simulate`, process runtime) keeps its data directory (outbox, state file,
component logs) on a small tmpfs of its own. Once it streams metrics and runs a component that
crashes and is restarted over and over (each crash and restart is a component_status state
event), a filler file takes every byte left on that disk; then the cloud is killed for a few
seconds while the disk is still full, so nothing can be sent either; then the cloud comes back
and, later, the disk is freed. The agent keeps what the full disk cannot take in memory, metric
frames within its memory budget (``MEMORY_MIB``, enough for the whole scenario), so no point is
lost. Reported: metric points sent, stored, kept in memory and lost, where every lost point
must be one the agent counted as dropped (kept nowhere: disk full and memory budget spent; and
not sent: the cloud was gone), and state events: every crash the agent saw reached the cloud.
"""

from __future__ import annotations

import contextlib
import errno
import itertools
import os
import subprocess
import time
from pathlib import Path

from benchmarks._common import log
from benchmarks.chaos import Outcome
from benchmarks.chaos.rig import Agent, Cloud, kill_instances, settled_points, tail, wait_until

NAME = "diskfull"
INJECTS = "the agent's data disk (a small tmpfs) filled to the last byte, then the cloud killed meanwhile"

ROBOT = "chaos-diskfull"
SKILL = "flaky"
COMPONENT = "flapper"
DISK = "2m"
# The agent's memory budget for metric frames on a full disk (--outbox-memory): the default, which
# holds the long form's 2 minutes of 5 frames/s many times over, so the normal case loses nothing.
MEMORY_MIB = 8


def skill() -> dict:
    """One robot component that crashes 0.3 s after every start: a stream of state events."""
    return {
        "skill": "Flaky",
        "skill_id": SKILL,
        "components": {
            COMPONENT: {
                "name": "Flapper",
                "location": "robot",
                "ros": False,
                "resources": {"cpu": 0.1, "ram": 16},
                "robot": {"command": ["sh", "-c", "sleep 0.3; exit 3"]},
            }
        },
    }


def fill(directory: Path) -> int:
    """Take every free byte of the file system under ``directory``; return how many were taken."""
    taken = 0
    with (directory / "filler").open("wb", buffering=0) as filler:
        for size in (1 << 20, 1 << 12, 1):
            chunk = b"\0" * size
            while True:
                try:
                    taken += filler.write(chunk) or 0
                except OSError as exc:
                    if exc.errno != errno.ENOSPC:
                        raise
                    break
    return taken


def crash_events(cloud: Cloud) -> tuple[int, int, int]:
    """Return (crash events, give-up events, events out of order) the cloud stored for the component."""
    rows = cloud.sql(
        "SELECT coalesce(data->>'message', ''), ts FROM monitoring_event WHERE robot_id = %s AND component = %s"
        " AND kind = 'component_status' ORDER BY id",
        [ROBOT, COMPONENT],
    )
    crashes = sum("crashed (exit code" in m and "restart" in m for m, _ in rows)
    gave_up = sum("gave up" in m for m, _ in rows)
    disorder = sum(b[1] < a[1] for a, b in itertools.pairwise(rows))
    return crashes, gave_up, disorder


def run(quick: bool) -> list[Outcome]:
    """Fill the disk 10 s (2 min full), kill the cloud 3 s (1 min) meanwhile, and report what survived."""
    outage_s = 3.0 if quick else 60.0
    full_s = 10.0 if quick else 120.0
    outcome = Outcome(scenario=NAME, injected=f"disk full {full_s:g} s, cloud down {outage_s:g} s of it")
    cloud = Cloud(NAME)
    disk = cloud.dir / "disk"
    disk.mkdir()
    subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={DISK}", "tmpfs", str(disk)], check=True)
    agent: Agent | None = None
    kill_instances(ROBOT, SKILL)
    try:
        cloud.start()
        token, api_token = cloud.add_robot(ROBOT, config={"offloading": "robot"}, skills=[skill()])
        agent = Agent(
            ROBOT,
            token,
            cloud.server.ws_url,
            disk / "agent",
            cloud.dir / "agent.log",
            sample_interval=0.2,
            options=["--outbox-memory", str(MEMORY_MIB)],
        )
        wait_until(lambda: (agent.try_scrape() or {}).get("bridgeos_agent_link_up") == 1, "the agent connected", 60)
        response = cloud.api(api_token, "POST", f"/api/robot/{ROBOT}/skill/{SKILL}/start", params={"wait": 20})
        if response.status_code != 200:
            raise RuntimeError(f"starting the Skill: {response.status_code} {response.text[:500]}")
        taken = fill(disk)
        log(f"diskfull: the agent's disk is full ({taken} bytes taken)")
        filled_at = time.monotonic()
        time.sleep(2.0)
        cloud.server.kill()
        time.sleep(outage_s)
        cloud.server.start()
        time.sleep(max(0.0, filled_at + full_s - time.monotonic()))
        during = agent.scrape()
        (disk / "filler").unlink()
        freed_at = time.monotonic()
        log("diskfull: disk freed")

        # Settled: nothing owed, nothing unstored in flight, the disk writable again.
        after, stored, duplicated = settled_points(agent, cloud, ROBOT, timeout=90)
        recover_s = time.monotonic() - freed_at
        alive = agent.alive()
        said = "disk full under the outbox" in agent.log_text()
        sent = int(after.get("bridgeos_agent_metric_points_sent_total", 0))
        dropped = int(after.get("bridgeos_agent_metric_points_dropped_total", 0))
        unstored = int(after.get("bridgeos_agent_outbox_unstored_points_total", 0))
        in_memory = int(after.get("bridgeos_agent_outbox_spilled_points_total", 0))
        lost = max(0, sent - (stored - duplicated))
        restarts = int(after.get("bridgeos_agent_component_restarts_total", 0))
        crashes, gave_up, disorder = crash_events(cloud)
        outcome.sent, outcome.stored, outcome.lost, outcome.duplicated = sent, stored, lost, duplicated
        outcome.figures = {
            "metric_points_unstored": unstored,
            "metric_points_dropped": dropped,
            "metric_points_kept_in_memory": in_memory,
            "state_events_crashes_seen": restarts,
            "state_events_crashes_stored": crashes,
            "state_events_gave_up_stored": gave_up,
            "state_events_lost": max(0, restarts - crashes),
            "state_events_out_of_order": disorder,
            "disk_full_seen": int(during.get("bridgeos_agent_outbox_disk_full", 0) or in_memory + unstored > 0),
        }
        checks = {
            "the agent died": alive,
            "the agent did not say its disk was full": said,
            "the outbox never met the full disk (no metric point kept in memory)": in_memory > 0,
            f"{unstored} point(s) not kept within a {MEMORY_MIB} MiB memory budget": unstored == 0,
            f"{lost} point(s) lost but {dropped} counted as dropped": lost == dropped,
            f"{duplicated} point(s) duplicated": duplicated == 0,
            # Read after the agent's count: a crash in between may add an event, never remove one.
            f"{restarts} crash(es) seen, {crashes} crash event(s) stored": restarts > 0 and crashes >= restarts,
            f"{gave_up} give-up events": gave_up <= 1,
            f"{disorder} state event(s) out of order": disorder == 0,
        }
        failed = [what for what, ok in checks.items() if not ok]
        outcome.passed = not failed
        outcome.detail = "; ".join(failed) or (
            f"{in_memory} points kept in memory on the full disk, {unstored} not kept, {dropped} dropped and counted; "
            f"{crashes}/{restarts} crash events delivered"
        )
        outcome.recover_s = round(recover_s, 2)
    except Exception as exc:
        outcome.detail = f"{exc}\n{tail(cloud.dir / 'agent.log')}"
        raise
    finally:
        if agent is not None:
            agent.stop()
        cloud.stop()
        kill_instances(ROBOT, SKILL)
        with contextlib.suppress(OSError):
            (disk / "filler").unlink()
        if subprocess.run(["umount", str(disk)], capture_output=True).returncode != 0:
            subprocess.run(["umount", "-l", str(disk)], capture_output=True)
        with contextlib.suppress(OSError):
            os.rmdir(disk)
    return [outcome]

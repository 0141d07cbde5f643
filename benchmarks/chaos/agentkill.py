"""Kill the agent with `kill -9` while it holds a backlog and runs a component; restart it.

The real `bridgeos-agent run --simulate --runtime process` runs a Skill whose one component (a
shell that notes its pid in a file, then sleeps) was started by the cloud's `skill_start`. The
cloud goes away (daphne killed), the robot keeps measuring into its outbox, and the agent is
killed with -9. The outbox left on disk is the backlog. The agent is started again, then the
cloud: the component must be re-adopted (same process, started once), every backlog point
stored once and in the order it was made, and the `skill_start` applied once.
"""

from __future__ import annotations

import json
import os
import shutil
import sqlite3
import sys
import time
import urllib.request
import uuid
from pathlib import Path

import psycopg

from benchmarks.chaos import Outcome
from benchmarks.chaos.rig import Agent, Cloud, api_token, create_robots, wait_until

NAME = "agentkill"
INJECTS = "agent kill -9 with a backlog (cloud down) and a running component, then restarted"
SKILL = "sleeper"


def _skill_config(starts: Path) -> dict:
    """A Skill of one robot component that notes each start of it and then sleeps."""
    return {
        "skill": "Sleeper",
        "skill_id": SKILL,
        "components": {
            "sleeper": {
                "name": "Sleeper",
                "location": "robot",
                "ros": False,
                "resources": {"cpu": 0.1, "ram": 16},
                "robot": {"command": ["sh", "-c", f"echo $$ >> {starts}; exec sleep 100000"]},
            }
        },
    }


def _post(base: str, path: str, token: str, body: dict | None = None) -> dict:
    request = urllib.request.Request(
        base + path,
        data=json.dumps(body or {}).encode(),
        headers={"Authorization": f"Token {token}", "Content-Type": "application/json"},
        method="POST",
    )
    with urllib.request.urlopen(request, timeout=60) as response:
        return json.loads(response.read() or b"{}")


def _robot_connected(database_url: str, robot: str) -> bool:
    with psycopg.connect(database_url, autocommit=True) as conn:
        row = conn.execute("SELECT connected FROM robots_robot WHERE id = %s", [robot]).fetchone()
    return bool(row and row[0])


def _backlog(outbox: Path) -> list[tuple[int, str, list[tuple[str, str, str, float]]]]:
    """Read the killed agent's outbox: (seq, frame id, points) of every metrics frame it owes."""
    db = sqlite3.connect(outbox)
    try:
        rows = db.execute("SELECT seq, id, frame FROM outbox WHERE metrics ORDER BY seq").fetchall()
    finally:
        db.close()
    frames = []
    for seq, frame_id, text in rows:
        points = json.loads(text)["data"]["metrics"]
        series = [(p["name"], p.get("skill") or "", p.get("component") or "", p["ts"]) for p in points]
        frames.append((seq, frame_id, series))
    return frames


def _owed(outbox: Path) -> int:
    db = sqlite3.connect(outbox)
    try:
        return db.execute("SELECT count(*) FROM outbox").fetchone()[0]
    finally:
        db.close()


def _micros(ts: float) -> int:
    """Epoch microseconds of a point's ts, rounded as the cloud stores it."""
    second = int(ts)
    return second * 1_000_000 + round((ts - second) * 1e6)


def _stored(database_url: str, robot: str) -> list[tuple[int, str, str, str, int]]:
    """Every metric row of the robot: (row id, name, skill, component, ts in epoch microseconds)."""
    with psycopg.connect(database_url, autocommit=True) as conn:
        return conn.execute(
            "SELECT id, name, skill, component, (extract(epoch FROM ts) * 1000000)::bigint FROM monitoring_metric "
            "WHERE robot_id = %s ORDER BY id",
            [robot],
        ).fetchall()


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return Path(f"/proc/{pid}/stat").read_text().split(") ")[1][0] != "Z"


def run(quick: bool) -> list[Outcome]:
    """Play the kill once; one outcome."""
    cloud = Cloud(NAME)
    env, workdir, daphne = cloud.env, cloud.dir, cloud.server
    database = env["DATABASE_URL"]
    robot, token = create_robots(env, f"chaos-ak-{uuid.uuid4().hex[:6]}", 1)[0]
    key = api_token(env)
    starts = workdir / "starts"
    starts.touch()
    agent: Agent | None = None
    outbox = workdir / "agent" / "outbox.sqlite3"
    try:
        daphne.start()
        # Its components kept on exit, as a robot's are: the restarted agent must re-adopt them.
        agent = Agent(
            robot,
            token,
            daphne.ws_url,
            workdir / "agent",
            workdir / "agent.log",
            sample_interval=0.2,
            keep_components=True,
            options=("--firewall", "off"),
        )
        wait_until(lambda: _robot_connected(database, robot), "the agent connected", 60)
        base = f"http://127.0.0.1:{daphne.port}/api/robot/{robot}"
        _post(base, "/skill/add", key, {"config": _skill_config(starts)})
        _post(base, f"/skill/{SKILL}/start?wait=30", key)
        wait_until(lambda: starts.read_text().strip(), "the component started", 60)
        component_pid = int(starts.read_text().split()[0])
        time.sleep(1.0)
        # The cloud goes away: the robot keeps measuring into its outbox.
        daphne.kill()
        time.sleep(4.0 if quick else 15.0)
        agent.kill()
        backlog = _backlog(outbox)
        survived_kill = _alive(component_pid)
        agent.start()
        wait_until(lambda: "re-adopted" in agent.log_text() or agent.process.poll() is not None, "re-adopt", 30)
        time.sleep(1.0 if quick else 5.0)
        back_at = time.monotonic()
        daphne.start()
        wait_until(lambda: _owed(outbox) == 0, "the backlog acked", 90, interval=0.1)
        recover_s = round(time.monotonic() - back_at, 2)
        time.sleep(2.0)  # room for a second start of the component, were the skill_start applied again
        started = starts.read_text().split()
        still_running = _alive(component_pid)
        stored = _stored(database, robot)
        readopted = "re-adopted 1 running component" in agent.log_text()
    finally:
        if agent is not None:
            agent.stop()
        cloud.stop()
        # The agent leaves its components running on exit (for the next agent to adopt): end every copy here.
        for pid in {int(p) for p in starts.read_text().split()} if starts.exists() else ():
            if _alive(pid):
                os.killpg(pid, 9)
        if not os.environ.get("CHAOS_KEEP"):
            shutil.rmtree(workdir, ignore_errors=True)

    # Every backlog point stored once, and the frames stored in the order they were made.
    rows_of: dict[tuple[str, str, str, int], list[int]] = {}
    for row_id, name, skill, component, micros in stored:
        rows_of.setdefault((name, skill, component, micros), []).append(row_id)
    sent = stored_points = duplicated = 0
    first_rows = []
    for _, _, series in backlog:
        ids = []
        for name, skill, component, ts in series:
            sent += 1
            found = rows_of.get((name, skill, component, _micros(ts)), [])
            stored_points += bool(found)
            duplicated += max(0, len(found) - 1)
            ids += found
        if ids:
            first_rows.append(min(ids))
    in_order = first_rows == sorted(first_rows)
    all_duplicates = sum(len(ids) - 1 for ids in rows_of.values())
    passed = (
        bool(backlog)
        and stored_points == sent
        and all_duplicates == 0
        and in_order
        and survived_kill
        and still_running
        and started == [str(component_pid)]
        and readopted
    )
    return [
        Outcome(
            scenario=NAME,
            injected=f"agent kill -9 with {len(backlog)} metrics frames owed and 1 component running",
            sent=sent,
            stored=stored_points,
            lost=sent - stored_points,
            duplicated=all_duplicates,
            recover_s=recover_s,
            passed=passed,
            detail=(
                f"component {'re-adopted' if readopted else 'NOT re-adopted'}, started {len(started)} time(s), "
                f"{'still running' if still_running else 'GONE'}; backlog {'in order' if in_order else 'OUT OF ORDER'}"
            ),
        )
    ]


if __name__ == "__main__":
    for outcome in run("--full" not in sys.argv):
        print(outcome)

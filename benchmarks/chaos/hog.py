"""A component that eats all the CPU and memory it can, on a robot run by the real agent's process runtime.

The hog declares 0.5 CPU and 100 MiB in its Skill config; it forks three busy processes (more
than the machine's cores) and grows its memory by 10 MiB every 0.4 s. The agent's process
runtime puts it in a control group (runtime/cgroups.py). Measured: the hog's CPU share while it
spins (must stay at its limit), its OOM kills (the kernel kills it past 100 MiB; the supervisor
restarts it and the cloud's event says why), and what the rest of the robot keeps: another
component printing a tick every 20 ms (its tick rate, against a baseline without the hog) and
the agent's own event loop (the latency of its /metrics endpoint, served from that loop).
The hog stops growing at 400 MiB by itself, so a machine without cgroups is not harmed.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import psutil

from benchmarks._common import log, percentile
from benchmarks.chaos import Outcome
from benchmarks.chaos.rig import Agent, Cloud, kill_instances, settled_points, tail, wait_until

NAME = "hog"
INJECTS = "a component eating every core and memory past its limits (0.5 CPU, 100 MiB)"

ROBOT = "chaos-hog"
STEADY, GREEDY = "steady", "greedy"
CPU_LIMIT, RAM_LIMIT = 0.5, 100
TICK_S = 0.02

HOG = """
import os, time
for _ in range(3):
    if os.fork() == 0:
        while True:
            pass
blocks = []
while len(blocks) < 40:
    blocks.append(bytearray(10 * 1024 * 1024))
    time.sleep(0.4)
time.sleep(3600)
"""
TICKER = f"""
import time
while True:
    print(time.time(), flush=True)
    time.sleep({TICK_S})
"""


def skill(skill_id: str, component: str, code: str, cpu: float, ram: float) -> dict:
    return {
        "skill": skill_id.title(),
        "skill_id": skill_id,
        "components": {
            component: {
                "name": component,
                "location": "robot",
                "ros": False,
                "resources": {"cpu": cpu, "ram": ram},
                "robot": {"command": [sys.executable, "-c", code]},
            }
        },
    }


def tick_rate(log_path: Path, start: float, end: float) -> float:
    """Return the ticker's ticks per second between two wall-clock times, from its own log."""
    count = 0
    for line in log_path.read_text(errors="replace").splitlines():
        try:
            stamp = float(line)
        except ValueError:
            continue
        count += start <= stamp < end
    return count / (end - start)


def component_cpu(robot: str, component: str, seconds: float) -> float:
    """Return the cores a component's processes used over ``seconds`` (every process, forked ones too)."""
    seen: dict[tuple[int, float], float] = {}
    first: dict[tuple[int, float], float] = {}
    started = time.monotonic()
    while time.monotonic() - started < seconds:
        for proc in psutil.process_iter(["pid"]):
            try:
                env = proc.environ()
                if env.get("BRIDGEOS_ROBOT") != robot or env.get("BRIDGEOS_COMPONENT") != component:
                    continue
                key = (proc.pid, proc.create_time())
                times = proc.cpu_times()
            except psutil.Error:
                continue
            seen[key] = times.user + times.system
            first.setdefault(key, seen[key])
        time.sleep(0.25)
    return sum(seen[k] - first[k] for k in seen) / (time.monotonic() - started)


def scrape_latencies(agent: Agent, count: int) -> list[float]:
    """Time ``count`` reads of the agent's /metrics endpoint (its event loop serves them), in ms."""
    latencies = []
    for _ in range(count):
        started = time.perf_counter()
        agent.scrape()
        latencies.append((time.perf_counter() - started) * 1000)
        time.sleep(0.05)
    return latencies


def oom_events(cloud: Cloud) -> int:
    rows = cloud.sql(
        "SELECT count(*) FROM monitoring_event WHERE robot_id = %s AND component = 'hog' AND data->>'message' LIKE %s",
        [ROBOT, "%memory limit%"],
    )
    return int(rows[0][0])


def run(quick: bool) -> list[Outcome]:
    """Run the ticker alone, then beside the hog (8 s quick, 2 min full), and report what the robot kept."""
    baseline_s = 3.0 if quick else 20.0
    hog_s = 8.0 if quick else 120.0
    outcome = Outcome(scenario=NAME, injected=f"CPU and memory hog for {hog_s:g} s")
    cloud = Cloud(NAME)
    agent: Agent | None = None
    for skill_id in (STEADY, GREEDY):
        kill_instances(ROBOT, skill_id)
    try:
        cloud.start()
        log("hog: cloud up")
        skills = [skill(STEADY, "ticker", TICKER, 0.2, 64), skill(GREEDY, "hog", HOG, CPU_LIMIT, RAM_LIMIT)]
        token, api_token = cloud.add_robot(ROBOT, config={"offloading": "robot"}, skills=skills)
        data_dir = cloud.dir / "agent"
        agent = Agent(ROBOT, token, cloud.server.ws_url, data_dir, cloud.dir / "agent.log")
        wait_until(lambda: (agent.try_scrape() or {}).get("bridgeos_agent_link_up") == 1, "the agent connected", 60)

        def start(skill_id: str) -> None:
            response = cloud.api(api_token, "POST", f"/api/robot/{ROBOT}/skill/{skill_id}/start", params={"wait": 20})
            if response.status_code != 200:
                raise RuntimeError(f"starting {skill_id}: {response.status_code} {response.text[:300]}")

        start(STEADY)
        ticks = data_dir / "runtime" / "logs" / STEADY / "ticker.log"
        wait_until(lambda: ticks.exists() and ticks.stat().st_size > 100, "the ticker ticking", 30)
        base_start = time.time()
        base_latency = scrape_latencies(agent, int(baseline_s / 0.06))
        base_end = time.time()
        base_rate = tick_rate(ticks, base_start, base_end)
        log(f"hog: baseline {base_rate:.1f} ticks/s, /metrics p99 {percentile(base_latency, 99):.1f} ms")

        start(GREEDY)
        hog_start = time.time()
        # The first 3 s: spinning on every core, memory still under the limit.
        hog_cores = component_cpu(ROBOT, "hog", 3.0)
        hog_latency = scrape_latencies(agent, max(10, int((hog_s - 3.0) / 0.06)))
        hog_end = time.time()
        hog_rate = tick_rate(ticks, hog_start, hog_end)
        stats = agent.scrape()
        restarts = int(stats.get("bridgeos_agent_component_restarts_total", 0))
        reported = wait_until(lambda: oom_events(cloud), "the OOM kill reported to the cloud", 20)
        stored_before = cloud.metric_rows(ROBOT)[0]
        time.sleep(1.5)
        # Everything the agent sent while the hog ran is stored: read when nothing is owed.
        settled, stored_after, duplicated = settled_points(agent, cloud, ROBOT, timeout=30)
        sent = int(settled.get("bridgeos_agent_metric_points_sent_total", 0))
        lost = max(0, sent - (stored_after - duplicated))
        outcome.sent, outcome.stored, outcome.lost, outcome.duplicated = sent, stored_after, lost, duplicated
        kept_rate = hog_rate / base_rate if base_rate else 0.0
        base_p99, hog_p99 = percentile(base_latency, 99) or 0.0, percentile(hog_latency, 99) or 0.0
        outcome.recover_s = None
        outcome.figures = {
            "hog_cpu_cores": round(hog_cores, 3),
            "hog_cpu_limit": CPU_LIMIT,
            "hog_oom_kills_reported": reported,
            "hog_restarts": restarts,
            "ticker_rate_kept": round(kept_rate, 3),
            "agent_loop_p99_ms_before": round(base_p99, 1),
            "agent_loop_p99_ms_during": round(hog_p99, 1),
            "agent_loop_p50_ms_before": round(percentile(base_latency, 50) or 0.0, 1),
            "agent_loop_p50_ms_during": round(percentile(hog_latency, 50) or 0.0, 1),
        }
        checks = {
            f"the hog used {hog_cores:.2f} cores over its {CPU_LIMIT} limit": hog_cores <= CPU_LIMIT * 1.15,
            "the hog was not OOM-killed and reported": reported >= 1 and restarts >= 1,
            # Starved would be far under half; a shared 2-core machine costs some wakeups even so.
            f"the ticker kept only {kept_rate:.0%} of its rate": kept_rate >= 0.6,
            f"the agent's loop p99 {hog_p99:.0f} ms (before {base_p99:.0f} ms)": hog_p99 <= max(250.0, 3 * base_p99),
            "the agent stopped storing metrics": stored_after > stored_before,
            f"{lost} metric point(s) lost, {duplicated} duplicated": lost == 0 and duplicated == 0,
            "the agent died": agent.alive(),
        }
        failed = [what for what, ok in checks.items() if not ok]
        outcome.passed = not failed
        outcome.detail = "; ".join(failed) or (
            f"hog held to {hog_cores:.2f} cores, OOM-killed {reported}x and restarted; ticker kept {kept_rate:.0%},"
            f" agent /metrics p99 {base_p99:.0f} -> {hog_p99:.0f} ms"
        )
    except Exception as exc:
        outcome.detail = f"{exc}\n{tail(cloud.dir / 'agent.log')}"
        raise
    finally:
        if agent is not None:
            agent.stop()
        cloud.stop()
        for skill_id in (STEADY, GREEDY):
            kill_instances(ROBOT, skill_id)
    return [outcome]

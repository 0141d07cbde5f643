"""Cloud components on Docker Swarm through the whole stack (issue 8; thesis §5.4 Figure 5.8).

1. A cloud component start as an operator asks for it - REST ``component/start`` → the robot
   (the real agent) → ``component_start`` → a Celery task → a Swarm service running - beside
   a bare ``docker service create`` of the same image and command with the same options
   (dnsrr, --init) timed to the same point (its task running), in the same run. Goal <=1.2x.
2. A migration robot → cloud → robot through REST ``migrate``, split into its phases from the
   cloud's event log: the command reaching the robot, the cloud copy's start (queue + Swarm),
   the switch (robot copy stopped, location reported), and back: the robot copy's start and
   the cloud copy's removal.
3. One robot's Skill of N cloud components (thesis: 250 per Skill, 0.89 +- 0.16 s per
   component init including its manager's neural network): how many run, the init time of
   each (request → running) and the wall time for all.

Everything is real: daphne, PostgreSQL, Redis, a two-process Celery worker, Swarm, and the
agent in this process (process runtime, simulated robot). Services carry a cloud id of the
benchmark's own and are all removed at the end.

    .venv/bin/python benchmarks/cloud_components.py --quick     # 1 start, 1 migration, 10 components
    .venv/bin/python benchmarks/cloud_components.py             # 10 starts, 3 migrations, 250 components
"""

from __future__ import annotations

import asyncio
import os
import statistics
import subprocess
import sys
import time
import uuid
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import Daphne, log
from _harness import arguments, cloud, report

IMAGE = "bridgeos/base:bookworm"
COMMAND = ["sleep", "3600"]
SKILL = "bench-cloud"
THESIS_INIT_S = (0.89, 0.16)
THESIS_COMPONENTS = 250


def skill_config(count: int, *, movable: bool = False) -> dict:
    from bridgeos_agent.skillconfig import parse_skill_config

    spec = {"image": IMAGE, "command": COMMAND}
    components = {
        f"c{n:03d}": {
            "name": f"Component {n}",
            "location": "either" if movable else "cloud",
            "ros": False,
            **({"robot": {"command": COMMAND}} if movable else {}),
            "cloud": spec,
        }
        for n in range(count)
    }
    return parse_skill_config({"skill": "Bench cloud", "skill_id": SKILL, "components": components}).model_dump(
        mode="json"
    )


# --------------------------------------------------------------------------- 1. start vs bare


def bare_service_start(name: str, network: str) -> float:
    """Time `docker service create` of the same service (image, command, options, an overlay network) to running."""
    command = ["docker", "service", "create", "--detach", "--quiet", "--name", name, "--endpoint-mode", "dnsrr"]
    command += ["--init", "--restart-condition", "none", "--network", network, "--label", "bridgeos-bench=cloud"]
    command += [IMAGE, *COMMAND]
    started = time.perf_counter()
    subprocess.run(command, check=True, capture_output=True)
    while True:
        states = subprocess.run(
            ["docker", "service", "ps", name, "--format", "{{.CurrentState}}"], capture_output=True, text=True
        ).stdout
        if states.startswith("Running"):
            break
        time.sleep(0.02)
    elapsed = time.perf_counter() - started
    # Removed and waited for, as the cloud's stop does, so each start finds the node in the same state.
    subprocess.run(["docker", "service", "rm", name], capture_output=True)
    while subprocess.run(
        ["docker", "ps", "-aq", "--filter", f"label=com.docker.swarm.service.name={name}"],
        capture_output=True,
        text=True,
    ).stdout.strip():
        time.sleep(0.05)
    return elapsed


async def wait_for(check, timeout: float = 120.0, interval: float = 0.02):
    deadline = time.monotonic() + timeout
    while True:
        value = await check()
        if value:
            return value
        if time.monotonic() > deadline:
            raise TimeoutError("condition not met in time")
        await asyncio.sleep(interval)


async def api_starts(api, robot_id: str, count: int) -> list[float]:
    """Start and stop one cloud component through the API `count` times; return the start times."""
    from asgiref.sync import sync_to_async

    from skills.models import CloudInstance

    @sync_to_async
    def status() -> str | None:
        row = CloudInstance.objects.filter(component__skill__robot_id=robot_id, component__component_id="c000").first()
        return row.status if row else None

    path = f"/api/robot/{robot_id}/skill/{SKILL}/component/c000"
    times = []
    # One more start than counted: the first creates the robot's overlay network, once per robot.
    for n in range(-1, count):
        started = time.perf_counter()
        answer = await api.post(path + "/start", json={"location": "cloud"}, params={"wait": 30})
        answer.raise_for_status()
        await wait_for(lambda: _is(status, "running"))
        elapsed = time.perf_counter() - started
        if n >= 0:
            times.append(elapsed)
        log(f"api start {n + 1}/{count}: {elapsed:.3f} s" + (" (the robot's first: not counted)" if n < 0 else ""))
        (await api.post(path + "/stop", json={"location": "cloud"}, params={"wait": 30})).raise_for_status()
        await wait_for(lambda: _is(status, "stopped"))
    return times


async def _is(read, wanted: str) -> bool:
    return await read() == wanted


# --------------------------------------------------------------------------- 2. migration phases


async def migrations(api, robot_id: str, count: int) -> list[dict[str, float]]:
    """Migrate one component robot → cloud → robot `count` times; return each one's phases."""
    from asgiref.sync import sync_to_async

    from monitoring.models import Event

    @sync_to_async
    def events_since(ts) -> list[Event]:
        return list(Event.objects.filter(robot_id=robot_id, component="c000", ts__gte=ts).order_by("ts", "id"))

    def first(events, predicate) -> float:
        for event in events:
            if predicate(event):
                return event.ts.timestamp()
        raise RuntimeError(f"an expected event is missing from the log: {[(e.kind, e.message) for e in events]}")

    path = f"/api/robot/{robot_id}/skill/{SKILL}/component/c000/migrate"
    results = []
    for n in range(count):
        from django.utils import timezone

        mark = timezone.now()
        t0 = time.time()
        answer = await api.post(path, json={"location": "cloud"}, params={"wait": 60})
        answer.raise_for_status()
        t_up = time.time()
        assert answer.json()["accepted"], answer.text
        events = await events_since(mark)
        migrating = first(events, lambda e: e.kind == "component_status" and "migrating" in e.message)
        requested = first(events, lambda e: e.kind == "component_start")
        running = first(events, lambda e: e.kind == "cloud_component_running")
        moved = first(events, lambda e: e.kind == "component_location")
        mark = timezone.now()
        t1 = time.time()
        answer = await api.post(path, json={"location": "robot"}, params={"wait": 60})
        answer.raise_for_status()
        t_down = time.time()
        assert answer.json()["accepted"], answer.text
        stopped = await wait_for(lambda m=mark: _stopped_event(events_since, m), timeout=60)
        back = await events_since(mark)
        back_migrating = first(back, lambda e: e.kind == "component_status" and "migrating" in e.message)
        robot_running = first(back, lambda e: e.kind == "component_status" and "running on the robot" in e.message)
        phases = {
            "to_cloud_s": t_up - t0,
            "to_cloud_command_s": migrating - t0,
            "to_cloud_request_s": requested - migrating,
            "to_cloud_cloud_start_s": running - requested,
            "to_cloud_switch_s": moved - running,
            "to_robot_s": t_down - t1,
            "to_robot_command_s": back_migrating - t1,
            "to_robot_robot_start_s": robot_running - back_migrating,
            "to_robot_cloud_stop_s": stopped - robot_running,
        }
        results.append(phases)
        log(f"migration {n + 1}/{count}: to the cloud {phases['to_cloud_s']:.2f} s, back {phases['to_robot_s']:.2f} s")
    return results


async def _stopped_event(events_since, mark) -> float | None:
    for event in await events_since(mark):
        if event.kind == "cloud_component_stopped":
            return event.ts.timestamp()
    return None


# --------------------------------------------------------------------------- 3. many components


async def many(controller, robot_id: str, count: int) -> dict:
    """Start a Skill of `count` cloud components; return how many ran and each one's init time."""
    from asgiref.sync import sync_to_async

    from bridgeos_agent.skillconfig import parse_skill_config
    from monitoring.models import Event
    from skills.models import CloudInstance

    @sync_to_async
    def running() -> int:
        return CloudInstance.objects.filter(component__skill__robot_id=robot_id, status="running").count()

    @sync_to_async
    def init_times() -> list[float]:
        asked, up = {}, {}
        for event in Event.objects.filter(robot_id=robot_id, kind__in=("component_start", "cloud_component_running")):
            (asked if event.kind == "component_start" else up).setdefault(event.component, event.ts.timestamp())
        return [up[c] - asked[c] for c in up if c in asked]

    started = time.perf_counter()
    await controller.start_skill(parse_skill_config(skill_config(count)))
    last, last_change = 0, time.monotonic()
    while True:
        now_running = await running()
        if now_running != last:
            last, last_change = now_running, time.monotonic()
            if now_running % 25 == 0 or now_running == count:
                log(f"{now_running}/{count} cloud components running")
        if now_running >= count or time.monotonic() - last_change > 120:
            break
        await asyncio.sleep(0.2)
    wall = time.perf_counter() - started
    return {"running": last, "wall_s": wall, "init_s": await init_times()}


# --------------------------------------------------------------------------- the run


async def run(args, env: dict[str, str], daphne: Daphne, api_token: str, tokens: dict[str, str], data: Path) -> dict:
    import httpx

    from bridgeos_agent.controller import AgentSettings, RobotController
    from bridgeos_agent.monitor import SimulatedRobot

    def agent(robot_id: str) -> RobotController:
        settings = AgentSettings(
            master=daphne.ws_url,
            robot=robot_id,
            token=tokens[robot_id],
            data_dir=data / robot_id,
            simulate=True,
            simulated=SimulatedRobot(cpu=64, ram=65536, seed=1),
            detect_ros_master=False,
            stop_components_on_exit=True,
            volume_sync_interval=0,
        )
        return RobotController(settings, plugins={}, say=lambda line: None)

    results: dict = {}
    headers = {"Authorization": f"Token {api_token}"}
    async with httpx.AsyncClient(base_url=f"http://127.0.0.1:{daphne.port}", headers=headers, timeout=90) as api:
        one = agent("bench-one")
        task = asyncio.create_task(one.run())
        try:
            await asyncio.wait_for(one.config_from_cloud.wait(), 30)
            from bridgeos_agent.skillconfig import parse_skill_config

            await one.start_skill(parse_skill_config(skill_config(1, movable=True)), starting=[])
            results["api"] = await api_starts(api, "bench-one", args.starts)
            await one.place_component(one.skills[SKILL], "c000", location="robot")
            results["migrations"] = await migrations(api, "bench-one", args.migrations)
        finally:
            one.stop()
            await asyncio.wait_for(task, 60)
        fleet = agent("bench-many")
        task = asyncio.create_task(fleet.run())
        try:
            await asyncio.wait_for(fleet.config_from_cloud.wait(), 30)
            results["many"] = await many(fleet, "bench-many", args.components)
        finally:
            fleet.stop()
            await asyncio.wait_for(task, 60)
    return results


def prepare(args) -> tuple[str, dict[str, str]]:
    """Create the operator and two robots; return the API token and the robots' tokens."""
    from django.contrib.auth import get_user_model

    from robots.models import Robot
    from robots.services import create_robot, issue_api_token
    from skills.services import add_skill

    Robot.objects.all().delete()
    owner, _ = get_user_model().objects.get_or_create(username="bench-cloud", defaults={"is_staff": True})
    tokens = {}
    configs = {"bench-one": skill_config(1, movable=True), "bench-many": skill_config(args.components)}
    for robot_id, config in configs.items():
        robot, tokens[robot_id] = create_robot(robot_id, owner)
        add_skill(robot, config)
    return issue_api_token(owner)[0], tokens


def remove_everything(cloud_id: str) -> None:
    """Remove every service and network of the benchmark's cloud id, and the bare ones."""
    for label in (f"io.bridgeos.cloud={cloud_id}", "bridgeos-bench=cloud"):
        names = subprocess.run(
            ["docker", "service", "ls", "-q", "--filter", f"label={label}"], capture_output=True, text=True
        ).stdout.split()
        for start in range(0, len(names), 100):
            subprocess.run(["docker", "service", "rm", *names[start : start + 100]], capture_output=True)
    deadline = time.monotonic() + 60
    while (
        time.monotonic() < deadline
        and subprocess.run(
            ["docker", "ps", "-aq", "--filter", f"label=io.bridgeos.cloud={cloud_id}"], capture_output=True, text=True
        ).stdout.strip()
    ):
        time.sleep(0.5)
    networks = []
    for label in (f"io.bridgeos.cloud={cloud_id}", "bridgeos-bench=cloud"):
        networks += subprocess.run(
            ["docker", "network", "ls", "-q", "--filter", f"label={label}"], capture_output=True, text=True
        ).stdout.split()
    if networks:
        subprocess.run(["docker", "network", "rm", *networks], capture_output=True)


def summary(values: list[float]) -> tuple[float | None, float | None]:
    if not values:
        return None, None
    return round(statistics.mean(values), 3), round(statistics.stdev(values), 3) if len(values) > 1 else 0.0


def main() -> int:
    parser = arguments(
        __doc__,
        "1 start, 1 migration, 10 components: under a minute",
        database="bridgeos_bench_cloud",
        redis=9,
        whole_doc=True,
    )
    parser.add_argument("--starts", type=int, default=10, help="API starts and bare service creates to time")
    parser.add_argument("--migrations", type=int, default=3, help="robot→cloud→robot round trips")
    parser.add_argument("--components", type=int, default=THESIS_COMPONENTS, help="cloud components of one Skill")
    args = parser.parse_args()
    if args.quick:
        args.starts, args.migrations, args.components = 1, 1, 10
    if min(args.starts, args.migrations, args.components) < 1:
        parser.error("every count must be at least 1")
    if subprocess.run(["docker", "image", "inspect", IMAGE], capture_output=True).returncode != 0:
        raise SystemExit(f"image {IMAGE} is not built: run docker/build-images.sh")

    cloud_id = f"bench-{uuid.uuid4().hex[:8]}"
    queue = f"{cloud_id}-q"
    env = {
        "BRIDGEOS_CLOUD_ID": cloud_id,
        "BRIDGEOS_CLOUD_RUNTIME": "swarm",
        "BRIDGEOS_CLOUD_ROS_MASTERS": "0",
        "CELERY_TASK_DEFAULT_QUEUE": queue,
        "BRIDGEOS_COMMAND_WAIT_S": "30",
    }
    try:
        with cloud(args, "bridgeos-bench-cloud-", env=env) as bench:
            import logging

            logging.getLogger("httpx").setLevel(logging.WARNING)
            load = os.getloadavg()
            log(f"load average before: {load[0]:.2f} {load[1]:.2f} {load[2]:.2f} on {os.cpu_count()} cores")
            api_token, tokens = prepare(args)
            daphne = bench.start_daphne(wait=False)
            celery = bench.start_celery(queue, wait=False)
            daphne.wait()
            celery.wait()
            log("bare `docker service create` of the same service, timed to its task running")
            network = f"bos-bench-bare-{cloud_id}"
            subprocess.run(
                [
                    "docker",
                    "network",
                    "create",
                    "-d",
                    "overlay",
                    "--attachable",
                    "--label",
                    "bridgeos-bench=cloud",
                    network,
                ],
                check=True,
                capture_output=True,
            )
            # The first start on a network sets it up on the node: timed apart, like the API's first start.
            bare_first = bare_service_start(f"bos-bench-bare-{cloud_id}-w", network)
            bare = [bare_service_start(f"bos-bench-bare-{cloud_id}-{n}", network) for n in range(args.starts)]
            log(f"bare: first {bare_first:.3f} s, then {statistics.mean(bare):.3f} s")
            results = asyncio.run(run(args, bench.env, daphne, api_token, tokens, bench.data_dir))
    finally:
        log("removing the benchmark's services")
        remove_everything(cloud_id)

    bare_mean, bare_sd = summary(bare)
    api_mean, api_sd = summary(results["api"])
    ratio = round(api_mean / bare_mean, 2) if api_mean and bare_mean else None
    phases = {key: round(statistics.mean(m[key] for m in results["migrations"]), 3) for key in results["migrations"][0]}
    many_result = results["many"]
    init_mean, init_sd = summary(many_result["init_s"])
    per_component_wall = round(many_result["wall_s"] / max(many_result["running"], 1), 3)
    load = os.getloadavg()

    print()
    print(f"Cloud components on Swarm through API, robot, Celery (2 worker processes); load {load[0]:.2f} on 2 cores")
    print(f"  start one cloud component via the API: {api_mean} +- {api_sd} s")
    print(
        f"  bare `docker service create` of the same service (overlay network, dnsrr, --init) to running: "
        f"{bare_mean} +- {bare_sd} s"
    )
    print(f"  swarm_over_bare = {ratio} (goal <= 1.2)")
    print(
        f"  migration robot->cloud {phases['to_cloud_s']} s: command {phases['to_cloud_command_s']} s, request "
        f"{phases['to_cloud_request_s']} s, cloud start {phases['to_cloud_cloud_start_s']} s, switch "
        f"{phases['to_cloud_switch_s']} s"
    )
    print(
        f"  migration cloud->robot {phases['to_robot_s']} s: command {phases['to_robot_command_s']} s, robot start "
        f"{phases['to_robot_robot_start_s']} s; cloud copy removed {phases['to_robot_cloud_stop_s']} s after"
    )
    print(
        f"  {many_result['running']}/{args.components} cloud components of one Skill running "
        f"(thesis: {THESIS_COMPONENTS} per Skill) in {many_result['wall_s']:.1f} s: init per component "
        f"{init_mean} +- {init_sd} s request->running, {per_component_wall} s of wall time each "
        f"(thesis {THESIS_INIT_S[0]} +- {THESIS_INIT_S[1]} s per component init)"
    )
    figures = {
        "swarm_over_bare": ratio,
        "migration_s": round(phases["to_cloud_s"] + phases["to_robot_s"], 3),
        "cloud_components": many_result["running"],
        "api_start_s": api_mean,
        "bare_service_start_s": bare_mean,
        "migration_to_cloud_s": phases["to_cloud_s"],
        "migration_to_robot_s": phases["to_robot_s"],
        "migration_phases_s": {k: v for k, v in phases.items() if k not in ("to_cloud_s", "to_robot_s")},
        "cloud_component_init_s": init_mean,
        "cloud_component_init_sd_s": init_sd,
        "cloud_components_wall_s": round(many_result["wall_s"], 1),
        "cloud_component_wall_s": per_component_wall,
        "load_average": round(load[0], 2),
    }
    report(figures)
    return 0


if __name__ == "__main__":
    sys.exit(main())

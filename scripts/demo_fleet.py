"""`make run`'s demo fleet: simulated robots running the real agent, each with the demo Skill started.

Every BRIDGEOS_DEMO_MOVE_S seconds (default 30; 0: never) it moves one robot's movable component
to the other side through the Robot API, so the dashboard shows components moving between the
robot and the cloud (where they run as Swarm services, or processes without Swarm).
"""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

from bridgeos_agent.tokenfile import write_token_file

ROOT = Path(__file__).resolve().parent.parent
BIN = ROOT / ".venv" / "bin"


def ros_ready() -> str | None:
    """Return why the use-case Skills cannot run here (no ROS master, no rospy/numpy), or None."""
    uri = os.environ.get("ROS_MASTER_URI", "http://127.0.0.1:11311")
    host, _, port = uri.removeprefix("http://").rstrip("/").partition(":")
    try:
        socket.create_connection((host, int(port or 11311)), timeout=1).close()
    except (OSError, ValueError):
        return f"no ROS master at {uri} (scripts/services.sh ros)"
    probe = subprocess.run(["/usr/bin/python3", "-c", "import rospy, numpy"], capture_output=True)
    if probe.returncode != 0:
        return "Debian's python3 lacks rospy or numpy (scripts/services.sh ros)"
    return None


def ros2_ready() -> str | None:
    """Return why the ROS 2 use-case Skills cannot run here (no rclpy in the agent's venv), or None."""
    probe = subprocess.run(
        [str(BIN / "python"), "-c", "import rclpy, sensor_msgs.msg, nav_msgs.msg"], capture_output=True
    )
    if probe.returncode != 0:
        return "no rclpy in the agent's venv (make install)"
    return None


def free_ports(count: int) -> list[int]:
    """Return ports nobody listens on right now, all different."""
    sockets = [socket.socket() for _ in range(count)]
    try:
        for sock in sockets:
            sock.bind(("127.0.0.1", 0))
        return [sock.getsockname()[1] for sock in sockets]
    finally:
        for sock in sockets:
            sock.close()


def main() -> int:
    count = int(os.environ.get("BRIDGEOS_DEMO_ROBOTS", "3"))
    host, port = os.environ.get("BRIDGEOS_HOST", "127.0.0.1"), os.environ.get("BRIDGEOS_PORT", "8000")
    owner = os.environ.get("DJANGO_SUPERUSER_USERNAME", "operator")
    if count <= 0:
        return 0
    why_not = ros_ready() if os.environ.get("BRIDGEOS_DEMO_USECASES", "1") != "0" else "BRIDGEOS_DEMO_USECASES=0"
    if why_not:
        print(f"== demo fleet: use-case Skills off: {why_not}", flush=True)
    why_not2 = ros2_ready() if os.environ.get("BRIDGEOS_DEMO_USECASES", "1") != "0" else "BRIDGEOS_DEMO_USECASES=0"
    if why_not2:
        print(f"== demo fleet: ROS 2 use-case Skills off: {why_not2}", flush=True)
    fleet = json.loads(
        subprocess.run(
            [str(BIN / "python"), "manage.py", "demo_fleet", "--count", str(count), "--owner", owner]
            + ([] if why_not else ["--usecases"])
            + ([] if why_not2 else ["--usecases2"]),
            cwd=ROOT,
            check=True,
            capture_output=True,
            text=True,
        ).stdout
    )
    data_root = Path(os.environ.get("BRIDGEOS_DATA_DIR", ROOT / ".data")) / "agents"
    data_root.mkdir(parents=True, exist_ok=True)
    agents = []
    # Each agent serves Prometheus metrics on its own loopback port (from BRIDGEOS_DEMO_METRICS_PORT
    # on, else free ones); Prometheus finds them in this file.
    metrics_base = os.environ.get("BRIDGEOS_DEMO_METRICS_PORT")
    ports = (
        [int(metrics_base) + n for n in range(len(fleet["robots"]))]
        if metrics_base
        else free_ports(len(fleet["robots"]))
    )
    targets = [f"127.0.0.1:{port}" for port in ports]
    (data_root / "prometheus-targets.json").write_text(json.dumps([{"targets": targets}]))
    domain_base = int(os.environ.get("BRIDGEOS_DEMO_ROS_DOMAIN", "100"))
    for number, (robot, metrics_address) in enumerate(zip(fleet["robots"], targets, strict=True)):
        log = (data_root / f"{robot['id']}.log").open("ab")
        # Through a token file (mode 600), not visible in `ps`; a robot re-keyed live keeps its new
        # token there, so an agent that restarts logs in with it.
        token_file = data_root / robot["id"] / "token"
        token_file.parent.mkdir(parents=True, exist_ok=True)
        write_token_file(token_file, robot["token"])
        env = {k: v for k, v in os.environ.items() if k != "BRIDGEOS_TOKEN"} | {"BRIDGEOS_TOKEN_FILE": str(token_file)}
        # Each demo robot's ROS 2 graph: a domain of its own, kept on this host (they all share it).
        env.setdefault("ROS_DOMAIN_ID", str((domain_base + number) % 233))
        env.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
        env.setdefault("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp")
        agents.append(
            subprocess.Popen(
                [
                    str(BIN / "bridgeos-agent"),
                    "run",
                    "--master",
                    f"ws://{host}:{port}",
                    "--robot",
                    robot["id"],
                    "--data-dir",
                    str(data_root / robot["id"]),
                    "--simulate",
                    # What the robot's config declares (demo_fleet's DEMO_ROBOT), and its link's low point.
                    "--sim-cpu",
                    str(robot["simulate"]["cpu"]),
                    "--sim-ram",
                    str(robot["simulate"]["ram"]),
                    "--sim-bandwidth",
                    str(robot["simulate"]["bandwidth"]),
                    "--sim-bandwidth-min",
                    str(robot["simulate"]["bandwidth_min"]),
                    "--stop-components-on-exit",
                    "--metrics",
                    metrics_address,
                ],
                env=env,
                stdout=log,
                stderr=subprocess.STDOUT,
            )
        )
    print(f"== demo fleet: {len(agents)} simulated robots (logs in {data_root})", flush=True)
    headers = {"Authorization": f"Token {fleet['api_token']}"}
    base = f"http://{host}:{port}/api/robot"
    for robot in fleet["robots"]:
        # Wait until the robot is online (its agent connected), then start its Skill.
        for _ in range(120):
            try:
                info = urllib.request.urlopen(urllib.request.Request(f"{base}/{robot['id']}/info", headers=headers))
                if json.loads(info.read())["connected"]:
                    break
            except OSError:
                pass  # the cloud is still starting
            time.sleep(0.25)
        for skill in robot.get("skills", [robot["skill"]]):
            # A robot busy starting its other Skills' components answers late on a loaded machine: wait.
            url = f"{base}/{robot['id']}/skill/{skill}/start?wait=30"
            for attempt in range(5):
                try:
                    urllib.request.urlopen(urllib.request.Request(url, method="POST", headers=headers), timeout=40)
                    break
                except OSError as exc:
                    # "connected" may be left over from a cloud that was killed: the agent's new
                    # connection replaces it within moments, so try again.
                    if attempt == 4:
                        print(f"== demo fleet: could not start {skill} on {robot['id']}: {exc}", flush=True)
                    time.sleep(1)
    signal.signal(signal.SIGTERM, lambda *_: stop(agents))
    signal.signal(signal.SIGINT, lambda *_: stop(agents))
    move_every = float(os.environ.get("BRIDGEOS_DEMO_MOVE_S", "30"))
    if move_every > 0:
        move_components(fleet, base, headers, move_every, agents)
    for agent in agents:
        agent.wait()
    return 0


def move_components(fleet: dict, base: str, headers: dict, every: float, agents: list[subprocess.Popen]) -> None:
    """Every `every` seconds, move one demo robot's movable component to the other side, round robin."""
    movable = ("filter", "planner")
    turn = 0
    while all(agent.poll() is None for agent in agents):
        time.sleep(every)
        robot = fleet["robots"][turn % len(fleet["robots"])]
        component = movable[(turn // len(fleet["robots"])) % len(movable)]
        turn += 1
        url = f"{base}/{robot['id']}/skill/{robot['skill']}/component/{component}/migrate?wait=60"
        started = time.monotonic()
        try:
            answer = json.loads(
                urllib.request.urlopen(urllib.request.Request(url, method="POST", headers=headers), timeout=70).read()
            )
        except OSError as exc:
            print(f"== demo fleet: moving {robot['id']}/{component} failed: {exc}", flush=True)
            continue
        took = time.monotonic() - started
        if answer.get("accepted"):
            print(f"== demo fleet: moved {robot['id']}/{component} to the other side ({took:.1f} s)", flush=True)
        else:
            why = (answer.get("reply") or {}).get("data", {}).get("message", "refused")
            print(f"== demo fleet: {robot['id']}/{component} not moved: {why}", flush=True)


def stop(agents: list[subprocess.Popen]) -> None:
    for agent in agents:
        agent.terminate()
    for agent in agents:
        agent.wait(timeout=30)
    sys.exit(0)


if __name__ == "__main__":
    sys.exit(main())

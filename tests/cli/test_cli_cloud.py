"""`bridgeos`, installed in its own venv, run as a subprocess against a live cloud (daphne) and a real agent."""

from __future__ import annotations

import json
import stat
from pathlib import Path

import pytest
from django.conf import settings
from django.contrib.auth import get_user_model
from django.utils import timezone

from recordings.models import Recording
from registry.models import RegistryTag
from robots.models import Robot
from robots.services import create_robot
from skills.models import Skill
from teams.services import personal_organization
from tests.browser.conftest import start_agent, stop_agent
from tests.cli.conftest import lines_of, next_line, stop
from tests.conftest import ROOT, wait_until

pytestmark = [pytest.mark.slow, pytest.mark.django_db(transaction=True)]

PASSWORD = "cli-pass-123!"
SAMPLE = ROOT / "agent" / "src" / "bridgeos_agent" / "samples" / "demo_telemetry.json"
SKILL = "cli-r1/demo-telemetry"


@pytest.fixture
def ann(daphne_server):
    """A user with one robot, and another user with a robot of theirs she must never see."""
    users = get_user_model().objects
    ann = users.create_user("cli-ann", password=PASSWORD)
    bob = users.create_user("cli-bob", password=PASSWORD)
    create_robot("cli-bob-r", bob)
    return ann


def test_a_wrong_password_is_refused_with_the_apis_words_and_keeps_nothing(cli, ann, daphne_server):
    wrong = cli("login", daphne_server.url, "-u", "cli-ann", "--password", "nope")
    assert wrong.code == 3, wrong
    assert "Login refused: Invalid username/password." in wrong.err, wrong
    assert not cli.config_file.exists()
    # A URL that is no bridgeOS cloud: its status and where, not the page it served.
    astray = cli("login", daphne_server.url + "/nothing", "-u", "cli-ann", "--password", PASSWORD)
    assert astray.code == 4 and f"HTTP 404 Not Found from {daphne_server.url}/nothing/api/auth" in astray.err, astray
    assert not cli.config_file.exists()


def test_login_keeps_a_token_only_its_user_reads_and_logout_forgets_it(cli, ann, daphne_server):
    logged = cli("login", daphne_server.url + "/", input=f"cli-ann\n{PASSWORD}\n")
    assert logged.code == 0 and f"Logged in to {daphne_server.url} as cli-ann" in logged.out, logged
    assert stat.S_IMODE(cli.config_file.stat().st_mode) == 0o600
    assert stat.S_IMODE(cli.config_file.parent.stat().st_mode) == 0o700
    stored = json.loads(cli.config_file.read_text())
    assert stored["url"] == daphne_server.url and stored["username"] == "cli-ann"

    me = cli("whoami", "--json")
    assert me.code == 0 and me.json()["robots"] == 0, me
    # $XDG_CONFIG_HOME, when set, is where the login lives: there is none there.
    elsewhere = cli("whoami", XDG_CONFIG_HOME=str(cli.home / "elsewhere"))
    assert elsewhere.code == 3 and "Not logged in" in elsewhere.err, elsewhere
    # The environment overrides the stored login: a wrong token is refused in the API's words.
    bogus = cli("robots", "ls", BRIDGEOS_TOKEN="not-a-token")
    assert bogus.code == 3 and "Invalid or expired token" in bogus.err and "bridgeos login" in bogus.err, bogus
    live = cli("events", "-f", BRIDGEOS_TOKEN="not-a-token")
    assert live.code == 3 and "The cloud refused the token" in live.err, live

    assert cli("logout").code == 0 and not cli.config_file.exists()
    assert cli("robots", "ls").code == 3
    # A token made elsewhere (CI) logs in as it is, and works from the environment alone too.
    again = cli("login", daphne_server.url, "--token", stored["token"], "--json")
    assert again.code == 0 and again.json()["url"] == daphne_server.url, again
    assert cli("logout").code == 0
    env_only = cli("robots", "ls", "--json", BRIDGEOS_URL=daphne_server.url, BRIDGEOS_TOKEN=stored["token"])
    assert env_only.code == 0 and env_only.json() == [], env_only


def test_every_command_against_a_live_cloud_and_a_real_agent(cli, ann, daphne_server, tmp_path):
    _, robot_token = create_robot("cli-r1", ann, name="CLI robot")
    assert cli("login", daphne_server.url, "-u", "cli-ann", "--password", PASSWORD).code == 0
    data_dir, log = tmp_path / "agent", tmp_path / "agent.log"
    agent = start_agent(daphne_server.ws_url, "cli-r1", robot_token, data_dir, log=log)
    try:
        wait_until(lambda: Robot.objects.filter(id="cli-r1", connected=True).exists(), 20, "the agent to connect")
        robots_and_skills(cli, tmp_path)
        events(cli)
        metrics(cli)
        printed_logs(cli, tmp_path)
    finally:
        stop_agent(agent, data_dir, log)
    recordings(cli, tmp_path)
    images(cli, ann)
    releases_and_rollouts(cli, tmp_path)


def robots_and_skills(cli, tmp_path: Path) -> None:
    listed = cli("robots", "ls", "--json")
    assert listed.code == 0 and [robot["id"] for robot in listed.json()] == ["cli-r1"], listed
    table = cli("robots", "ls").out.splitlines()
    assert table[0].split()[:3] == ["ID", "NAME", "STATUS"] and table[1].startswith("cli-r1 ")
    assert cli("robots", "show", "cli-r1", "--json").json()["connected"] is True
    for hidden in ("cli-bob-r", "nobody"):
        refused = cli("robots", "show", hidden)
        assert refused.code == 4 and "No such robot." in refused.err, refused

    bad = json.loads(SAMPLE.read_text())
    bad["components"]["sensor"]["resources"]["cpu"] = -1
    (tmp_path / "bad.json").write_text(json.dumps(bad))
    invalid = cli("skills", "add", "cli-r1", "-f", str(tmp_path / "bad.json"))
    assert invalid.code == 1 and "components.sensor.resources.cpu" in invalid.err, invalid
    added = cli("skills", "add", "cli-r1", "-f", str(SAMPLE), "--json")
    assert added.code == 0 and added.json()["skill_id"] == "demo-telemetry", added
    assert [skill["skill_id"] for skill in cli("skills", "ls", "cli-r1", "--json").json()] == ["demo-telemetry"]

    started = cli("skills", "start", SKILL, "--wait", "20", "--json")
    assert started.code == 0 and started.json()["accepted"] is True, started
    wait_until(
        lambda: {c["status"] for c in cli("skills", "show", SKILL, "--json").json()["components"]} == {"running"},
        20,
        "the Skill's components to run",
        interval=0.5,
    )
    assert "sensor" in cli("skills", "show", SKILL).out
    shown = cli("components", "show", f"{SKILL}/sensor", "--json")
    assert shown.json()["active_location"] == "robot", shown
    # The sensor may only run on the robot: the API says why, naming the field.
    refused = cli("components", "migrate", f"{SKILL}/sensor", "--to", "cloud")
    assert refused.code == 1 and "location" in refused.err, refused
    stopped = cli("components", "stop", f"{SKILL}/planner", "--wait", "20", "--json")
    assert stopped.code == 0 and stopped.json()["accepted"], stopped
    restarted = cli("components", "start", f"{SKILL}/planner", "--at", "robot", "--wait", "20")
    assert restarted.code == 0 and "accepted by cli-r1" in restarted.out, restarted

    assert cli("skills", "stop", SKILL, "--wait", "20").code == 0
    wait_until(lambda: Skill.objects.get(robot_id="cli-r1").status == "stopped", 20, "the Skill to stop")
    removed = cli("skills", "remove", SKILL)
    assert removed.code == 0 and not Skill.objects.filter(robot_id="cli-r1").exists(), removed
    missing = cli("skills", "start", "cli-r1/nothing-here")
    assert missing.code == 4, missing


def events(cli) -> None:
    logged = cli("events", "-r", "cli-r1", "--json")
    assert logged.code == 0 and "skill_added" in {event["kind"] for event in logged.json()}, logged
    assert "skill_added" in cli("events", "-r", "cli-r1", "--since", "1h").out
    follow = cli.popen("events", "-f", "-r", "cli-r1", "-n", "0", "--json")
    try:
        received = lines_of(follow)
        assert cli("skills", "add", "cli-r1", "-f", str(SAMPLE)).code == 0
        line = next_line(received, follow, lambda text: json.loads(text)["kind"] == "skill_added")
        assert json.loads(line)["robot"] == "cli-r1"
    finally:
        stop(follow)


def metrics(cli) -> None:
    rows = wait_until(
        lambda: cli("metrics", "query", "-r", "cli-r1", "--since", "10m", "--json").json(),
        20,
        "the agent's metrics",
        interval=0.5,
    )
    assert {row["robot"] for row in rows} == {"cli-r1"} and "cpu" in {row["name"] for row in rows}
    table = cli("metrics", "query", "-r", "cli-r1", "-m", "cpu", "-a", "max", "-b", "60")
    assert table.code == 0 and "cpu" in table.out, table
    foreign = cli("metrics", "query", "-r", "cli-bob-r")
    assert foreign.code == 1 and "robots: No robot 'cli-bob-r'." in foreign.err, foreign


def recordings(cli, tmp_path: Path) -> None:
    content = bytes(range(256)) * 4096  # 1 MiB: the progress bar moves
    relative = Path("cli-r1") / "cli.mcap"
    path = Path(settings.BRIDGEOS["RECORDINGS_DIR"]) / relative
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(content)
    now = timezone.now()
    recording = Recording.objects.create(
        robot_id="cli-r1",
        topics=["/chatter"],
        status="finished",
        max_bytes=1 << 30,
        max_duration_s=60,
        started_at=now,
        stopped_at=now,
        size_bytes=len(content),
        file=str(relative),
    )
    listed = cli("recordings", "ls", "cli-r1", "--json")
    assert [item["id"] for item in listed.json()] == [recording.id.hex], listed
    assert recording.id.hex in cli("recordings", "ls", "cli-r1").out
    target = tmp_path / "downloaded.mcap"
    fetched = cli("recordings", "download", "cli-r1", recording.id.hex, "-o", str(target))
    assert fetched.code == 0 and target.read_bytes() == content, fetched
    assert "downloaded.mcap" in fetched.err  # the progress bar's label
    assert not (tmp_path / "downloaded.mcap.part").exists()
    gone = cli("recordings", "download", "cli-r1", "0" * 32)
    assert gone.code == 4, gone


def printed_logs(cli, tmp_path: Path) -> None:
    """`logs -f` prints a line a component on the real agent printed, shipped by the agent through the cloud."""
    talk = ["sh", "-c", 'n=0; while true; do n=$((n + 1)); echo "[WARN] hello $n"; sleep 0.2; done']
    component = {"name": "talk", "location": "robot", "ros": False, "resources": {"cpu": 0.1, "ram": 16}}
    config = {
        "skill": "Talker",
        "skill_id": "talker",
        "components": {"talk": {**component, "robot": {"command": talk}}},
    }
    (tmp_path / "talker.json").write_text(json.dumps(config))
    assert cli("skills", "add", "cli-r1", "-f", str(tmp_path / "talker.json")).code == 0
    follow = cli.popen("logs", "-f", "cli-r1/talker/talk", "-n", "0", "--level", "warning")
    try:
        received = lines_of(follow)
        assert cli("skills", "start", "cli-r1/talker").code == 0
        line = next_line(received, follow, lambda text: "hello" in text)
        assert "robot" in line and "talker/talk: [WARN] hello " in line, line
    finally:
        stop(follow)
    assert cli("skills", "stop", "cli-r1/talker").code == 0


def images(cli, ann) -> None:
    namespace = personal_organization(ann).slug
    RegistryTag.objects.create(
        repository=f"{namespace}/detector",
        namespace=namespace,
        tag="1.0",
        digest="sha256:" + "ab" * 32,
        size=1234,
        pushed_by="cli-ann",
        pushed_at=timezone.now(),
    )
    listed = cli("images", "ls", "--json")
    assert [repo["repository"] for repo in listed.json()] == [f"{namespace}/detector"], listed
    assert "sha256:abab" in cli("images", "ls").out


def releases_and_rollouts(cli, tmp_path: Path) -> None:
    config = json.loads(SAMPLE.read_text())
    for component in config["components"].values():
        component.pop("cloud", None)
        component["location"] = "robot"
    (tmp_path / "release.json").write_text(json.dumps(config))
    made = cli("releases", "create", "-f", str(tmp_path / "release.json"), "--name", "v1", "--json")
    assert made.code == 0 and made.json()["number"] == 1, made
    release = made.json()["id"]
    assert [item["id"] for item in cli("releases", "ls", "--json").json()] == [release]
    assert "v1" in cli("releases", "show", str(release)).out

    unknown = cli("rollouts", "create", "--release", "999999", "-l", "site=lab")
    assert unknown.code == 1 and "release: No release 999999 of yours." in unknown.err, unknown
    nobody = cli("rollouts", "create", "--release", str(release), "-l", "site=nowhere")
    assert nobody.code == 1 and "selector: 'site=nowhere' matches none" in nobody.err, nobody
    Robot.objects.filter(id="cli-r1").update(labels={"site": "cli"})
    started = cli("rollouts", "create", "--release", str(release), "-l", "site=cli", "--json")
    assert started.code == 0 and [robot["robot"] for robot in started.json()["robots"]] == ["cli-r1"], started
    rollout = str(started.json()["id"])
    assert [item["id"] for item in cli("rollouts", "ls", "--json").json()] == [int(rollout)]
    assert "cli-r1" in cli("rollouts", "show", rollout).out
    for action, state in (("pause", "paused"), ("resume", "running"), ("abort", "rolling_back")):
        steered = cli("rollouts", action, rollout, "--json")
        assert steered.code == 0 and steered.json()["state"] == state, (action, steered)
    again = cli("rollouts", "resume", rollout)
    assert again.code == 1 and again.err.startswith("Error: "), again
    assert cli("rollouts", "show", "999999").code == 4

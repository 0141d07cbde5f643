"""Property-based fuzzing of frames over a real socket: never a server error, never a state change."""

from __future__ import annotations

import json

import pytest
from django.contrib.auth import get_user_model
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st
from websockets.sync.client import connect

from bridgeos_agent import protocol
from bridgeos_agent.protocol import EVENTS, Direction, Event
from monitoring.models import Event as LogEvent
from monitoring.models import Metric
from robots.models import Robot
from robots.services import create_robot
from skills.models import Component, Skill

pytestmark = pytest.mark.django_db(transaction=True)

json_values = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats(allow_nan=False) | st.text(max_size=20),
    lambda children: st.lists(children, max_size=4) | st.dictionaries(st.text(max_size=10), children, max_size=4),
    max_leaves=12,
)
event_names = st.sampled_from(sorted(EVENTS)) | st.text(max_size=20)
ids = st.from_regex(r"[A-Za-z0-9_-]{1,12}", fullmatch=True) | st.text(max_size=70) | st.integers()
envelopes = st.fixed_dictionaries(
    {"event": event_names, "id": ids, "data": st.dictionaries(st.text(max_size=12), json_values, max_size=5)},
    optional={"reply_to": ids, "ts": json_values, "extra": json_values},
)
frames = st.one_of(
    envelopes.map(json.dumps),
    json_values.map(json.dumps),
    st.text(max_size=300),
    st.binary(max_size=300),
)
FUZZ = settings(max_examples=2000, deadline=None, suppress_health_check=list(HealthCheck), derandomize=True)


def state(robot_id: str = "fuzz-bot") -> tuple:
    """Return everything a frame from the robot could have changed."""
    return (
        LogEvent.objects.filter(robot_id=robot_id).count(),
        Metric.objects.filter(robot_id=robot_id).count(),
        list(Robot.objects.filter(id=robot_id).values_list("id", "status", "config")),
        list(Skill.objects.filter(robot_id=robot_id).values_list("skill_id", "status", "config").order_by("skill_id")),
        list(
            Component.objects.filter(skill__robot_id=robot_id)
            .values_list("component_id", "status", "active_location", "container")
            .order_by("id")
        ),
    )


@pytest.fixture
def robot_socket(daphne_server):
    owner = get_user_model().objects.create_user("owner")
    _, token = create_robot("fuzz-bot", owner)
    with connect(daphne_server.ws_url + "/ws/robot/", max_size=2**22) as ws:
        ws.send(
            json.dumps({"event": "authentication_robot", "id": "auth", "data": {"robot": "fuzz-bot", "token": token}})
        )
        for _ in range(3):
            frame = json.loads(ws.recv(timeout=5))
            if frame["event"] in protocol.REQUIRES_ACK:
                ws.send(protocol.encode(protocol.ack_frame(frame["id"], now=0)))
        yield ws


def test_fuzzed_frames_from_a_robot_never_break_the_server(robot_socket):
    before = state()
    counter = iter(range(10**9))

    @FUZZ
    @given(frame=frames)
    def check(frame):
        # A frame that happens to be a valid state change may change state: fuzz only the others.
        try:
            valid = protocol.decode(frame, direction=Direction.ROBOT_TO_CLOUD)
            assume(valid.event not in protocol.REQUIRES_ACK)
        except protocol.ProtocolError:
            pass
        robot_socket.send(frame)
        # A valid request right after tells us the fuzzed frame has been fully handled.
        sentinel = f"sentinel-{next(counter)}"
        robot_socket.send(json.dumps({"event": "robot_config_get", "id": sentinel, "data": {}}))
        while True:
            answer = json.loads(robot_socket.recv(timeout=10))
            assert answer["event"] in {"error_message", "ack", "robot_config"}, answer
            if answer["event"] == "error_message":
                assert answer["data"]["code"] != "internal_error", (frame, answer)
                assert "Traceback" not in answer["data"]["message"]
            if answer["event"] in protocol.REQUIRES_ACK:
                robot_socket.send(protocol.encode(protocol.ack_frame(answer["id"], now=0)))
            if answer.get("reply_to") == sentinel:
                break

    check()
    after = state()
    assert after == before, list(LogEvent.objects.values_list("kind", "message", "data"))


@settings(max_examples=200, deadline=None, suppress_health_check=list(HealthCheck), derandomize=True)
@given(frame=frames)
def test_any_fuzzed_first_frame_is_refused(daphne_server, frame):
    before = (LogEvent.objects.count(), Robot.objects.filter(connected=True).count())
    with connect(daphne_server.ws_url + "/ws/robot/") as ws:
        ws.send(frame)
        answer = protocol.decode(ws.recv(timeout=10))
        assert answer.event == Event.AUTHENTICATION_FAILURE
    assert (LogEvent.objects.count(), Robot.objects.filter(connected=True).count()) == before


def test_a_nul_byte_in_a_robots_error_report_is_logged_not_an_internal_error(robot_socket):
    # Found by the fault suite's fuzzer (benchmarks/chaos/hostile/): PostgreSQL refuses NUL in text.
    report = {"message": "disk\x00full", "field": "data.x\x00", "code": "no_space"}
    robot_socket.send(json.dumps({"event": "error_message", "id": "nul-report", "data": report}))
    robot_socket.send(json.dumps({"event": "robot_config_get", "id": "after-nul", "data": {}}))
    while True:
        answer = json.loads(robot_socket.recv(timeout=10))
        assert answer["event"] != "error_message", answer
        if answer["event"] in protocol.REQUIRES_ACK:
            robot_socket.send(protocol.encode(protocol.ack_frame(answer["id"], now=0)))
        if answer.get("reply_to") == "after-nul":
            break
    logged = LogEvent.objects.get(robot_id="fuzz-bot", kind="error_message")
    assert logged.message == "Robot reported: disk\ufffdfull"
    assert logged.data["field"] == "data.x\ufffd"


def test_a_nul_byte_in_a_reported_container_is_stored_not_an_internal_error(robot_socket):
    from bridgeos_agent.skillconfig import load_sample_skill_config
    from skills.services import add_skill

    add_skill(Robot.objects.get(id="fuzz-bot"), load_sample_skill_config().model_dump(mode="json"))
    container = {"id": "abc\x00", "runtime": "process"}
    data = {"skill": "people-detection", "component": "sampler", "location": "robot", "container": container}
    # A fresh id: the cloud remembers a robot's applied ids across connections, in Redis.
    frame_id = protocol.new_id()
    robot_socket.send(json.dumps({"event": "component_information", "id": frame_id, "data": data}))
    while True:
        answer = json.loads(robot_socket.recv(timeout=10))
        if answer["event"] in protocol.REQUIRES_ACK:
            robot_socket.send(protocol.encode(protocol.ack_frame(answer["id"], now=0)))
        if answer.get("reply_to") == frame_id:
            break
    assert answer["event"] == "ack", answer
    stored = Component.objects.get(skill__robot_id="fuzz-bot", component_id="sampler").container
    assert stored["robot"]["id"] == "abc\ufffd"

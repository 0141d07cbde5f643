"""Bytes-in, bytes-out tests of the robot⇄cloud⇄client protocol core."""

from __future__ import annotations

import ast
import json
from pathlib import Path
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from bridgeos_agent import protocol
from bridgeos_agent.protocol import (
    COMMANDS,
    DIRECTIONS,
    PAYLOADS,
    REPLIES,
    REQUIRES_ACK,
    Correlator,
    Dedup,
    Direction,
    Envelope,
    Event,
    IdGenerator,
    MetricsPayload,
    ProtocolError,
    Reliable,
    ack_frame,
    decode,
    encode,
    error_frame,
    is_allowed,
    make,
    parse_payload,
)

SAMPLES: dict[Event, dict[str, Any]] = {
    Event.AUTHENTICATION_CLIENT: {"token": "9944b09199c62bcf9418ad846dd0e4bbdfc6ee4b"},
    Event.AUTHENTICATION_ROBOT: {"robot": "turtlebot-1", "token": "s3cr3t_Tok-en"},
    Event.AUTHENTICATION_SUCCESS: {"robot": "turtlebot-1", "session": "abc123"},
    Event.AUTHENTICATION_FAILURE: {"reason": "invalid token"},
    Event.CONNECTION_ESTABLISHED: {"robot": "turtlebot-1"},
    Event.CONNECTION_LOST: {"robot": "turtlebot-1", "reason": "ping timeout"},
    Event.ERROR_MESSAGE: {"message": "bad", "field": "data.skill", "code": "invalid_payload"},
    Event.SHUTDOWN: {"reason": "maintenance"},
    Event.ROBOT_START: {},
    Event.ROBOT_STOP: {"robot": "turtlebot-1"},
    Event.ROBOT_CONFIG: {"config": {"robot": "turtlebot-1", "resources": {"cpu": 4}}},
    Event.ROBOT_CONFIG_GET: {},
    Event.ROBOT_CONFIG_UPDATE: {"changes": {"offloading": "auto"}},
    Event.OFFLOADING: {"mode": "auto"},
    Event.OFFLOADING_GET: {},
    Event.SKILL_START: {"skill": "people-detector", "config": {"skill": "people-detector"}},
    Event.SKILL_STOP: {"skill": "people-detector"},
    Event.SKILL_STATUS: {"skill": "people-detector", "status": "running"},
    Event.SKILL_STATUS_GET: {"skill": "people-detector"},
    Event.SKILL_CONNECT: {"skill": "people-detector", "manager_url": "http://127.0.0.1:9100/"},
    Event.SKILL_CONFIG: {"skill": "people-detector", "config": {"components": []}},
    Event.SKILL_CONFIG_GET: {"skill": "people-detector"},
    Event.COMPONENT_START: {"skill": "people-detector", "component": "detector", "location": "cloud"},
    Event.COMPONENT_STOP: {"skill": "people-detector", "component": "detector"},
    Event.COMPONENT_INFORMATION: {
        "skill": "people-detector",
        "component": "detector",
        "location": "robot",
        "container": {"id": "f00dcafe", "ip": "10.8.0.6", "image": "detector:1", "ports": [8080]},
    },
    Event.COMPONENT_STATUS: {
        "skill": "people-detector",
        "component": "detector",
        "status": "running",
        "location": "cloud",
    },
    Event.COMPONENT_STATUS_GET: {"skill": "people-detector", "component": "detector"},
    Event.COMPONENT_LOCATION: {"skill": "people-detector", "component": "detector", "location": "robot"},
    Event.COMPONENT_MIGRATE: {"skill": "people-detector", "component": "detector", "location": "cloud"},
    Event.METRICS: {
        "metrics": [
            {"name": "cpu", "value": 0.42, "ts": 1700000000.5},
            {
                "name": "ros.loss_rate",
                "value": 0.0,
                "ts": 1700000000.5,
                "skill": "people-detector",
                "component": "detector",
                "labels": {"topic": "/scan"},
            },
        ]
    },
    Event.METRICS_GET: {"names": ["cpu", "ram"], "skill": "people-detector", "since": 0, "limit": 10},
    Event.VOLUME_CHANGES: {
        "skill": "people-detector",
        "volume": "maps",
        "changes": [
            {"path": "floor/1.pgm", "size": 5, "mode": 0o644, "hash": "a" * 64, "chunks": ["a" * 64]},
            {"path": "old.yaml", "deleted": True},
        ],
    },
    Event.VOLUME_CHUNKS_GET: {
        "skill": "people-detector",
        "volume": "maps",
        "chunks": [{"path": "floor/1.pgm", "index": 0, "hash": "a" * 64}],
    },
    Event.VOLUME_CHUNKS: {
        "skill": "people-detector",
        "volume": "maps",
        "chunks": [{"hash": "a" * 64, "data": "aGVsbG8="}],
    },
    Event.ACK: {},
    Event.COMPONENTS_API: {
        "skill": "people-detector",
        "method": "POST",
        "path": "/components/detector/location",
        "query": "",
        "body": {"location": "cloud"},
    },
    Event.COMPONENTS_API_REPLY: {"skill": "people-detector", "status": 200, "body": {"location": "cloud"}},
    Event.LOG_EVENT: {
        "robot": "r1",
        "id": 7,
        "ts": "2026-11-27T13:00:00.000001Z",
        "level": "error",
        "source": "robot",
        "kind": "error_message",
        "skill": "",
        "component": "",
        "message": "Robot reported: no room",
        "data": {"code": "no_room"},
    },
    # recordings
    Event.RECORDING_START: {"recording": "0" * 32, "topics": ["/chatter"], "max_bytes": 1 << 20, "max_duration_s": 60},
    Event.RECORDING_STOP: {"recording": "0" * 32},
    Event.RECORDING_CHUNK: {"recording": "0" * 32, "seq": 0, "data": "iU1DQVAw"},
    Event.RECORDING_STATUS: {"recording": "0" * 32, "status": "finished", "messages": 3, "bytes": 90, "chunks": 1},
    Event.UPDATE_HOLD: {"skill": "people-detection", "component": "detector", "seconds": 600.0, "reason": "busy"},
    Event.ROBOT_REKEY: {"token": "brt_new-token"},
    Event.OFFLOADING_DECISION: {
        "skill": "people-detector",
        "component": "detector",
        "location": "robot",
        "target": "cloud",
        "outcome": "failed",
        "reason": "estimate above threshold + hysteresis",
        "error": "no room on the robot",
        "policy": "energy",
        "cost_robot": 1.5,
        "cost_cloud": 0.25,
        "estimated_reward": 1.25,
        "prediction": 1.1,
        "threshold": 0.1,
        "hysteresis": 0.05,
        "trained": True,
        "samples_seen": 1200,
        "inputs": {"cpu_available": 0.5, "location": "robot"},
        "decided_at": 1700000000.5,
        "duration_s": 0.25,
    },
    # bridges
    Event.BRIDGE_OPEN: {"session": "s3ss10n-a", "kind": "foxglove", "bytes_per_s": 1_000_000},
    Event.BRIDGE_FRAME: {"session": "s3ss10n-a", "binary": "AAEC", "more": True},
    Event.BRIDGE_CLOSE: {"session": "s3ss10n-a", "reason": "the client left"},
    # component logs
    Event.COMPONENT_LOGS: {
        "skill": "people-detector",
        "component": "detector",
        "location": "robot",
        "lines": [
            {"seq": 41, "ts": 1700000000.25, "stream": "stdout", "level": "info", "text": "[INFO] 3 people"},
            {"seq": 42, "ts": 1700000000.5, "stream": "stderr", "level": None, "text": "a line with no level"},
        ],
        "dropped": 7,
    },
    Event.COMPONENT_LOGS_GET: {"skill": "people-detector", "component": "detector", "after_seq": 40, "limit": 500},
    Event.LOGS_SUBSCRIBE: {"robot": "robot-1", "skill": "people-detector", "tail": 50, "ring": True},
    Event.LOGS_UNSUBSCRIBE: {"robot": "robot-1", "skill": "people-detector"},
    # the fleet page's live rows
    Event.METRICS_SUBSCRIBE: {"robots": ["robot-1", "robot-2"]},
}


def frame(event: str, data: Any = None, **envelope: Any) -> str:
    """Build raw frame text the way an outside client would."""
    body = {"event": event, "id": "m-1", "reply_to": None, "data": {} if data is None else data, "ts": 1.0}
    body.update(envelope)
    return json.dumps(body, ensure_ascii=False)


def rejection(text: str | bytes, **kwargs: Any) -> ProtocolError:
    with pytest.raises(ProtocolError) as caught:
        decode(text, **kwargs)
    return caught.value


def test_samples_cover_every_event_and_table() -> None:
    assert set(SAMPLES) == set(Event) == set(PAYLOADS) == set(DIRECTIONS)
    # Table 3.3's 31 events, ack, the three of Skill volume sync, the manager's decision log and the
    # cloud copies' Components API relay (request and reply), the event log's live entries, the three
    # of the bridges (a rosbridge/Foxglove client relayed over the robot's link), the four of MCAP
    # recordings, a connected robot's new token, a component's hold on its robot's updates, the four
    # of component logs (shipped, asked of a robot, a client's tail started and ended), and a client's
    # choice of the robots whose live metrics it is sent.
    assert len(Event) == 53
    assert REQUIRES_ACK <= set(Event) and COMMANDS <= REQUIRES_ACK
    # Requests are named *_get, but for the relayed Components API call, which may POST, a client's
    # live log tail, started and ended, and its live metrics narrowed to some robots.
    requests = {name for name in REPLIES if name not in COMMANDS and "auth" not in name} - {
        Event.COMPONENTS_API,
        Event.LOGS_SUBSCRIBE,
        Event.LOGS_UNSUBSCRIBE,
        Event.METRICS_SUBSCRIBE,
    }
    assert all(name.endswith("_get") for name in requests)


@pytest.mark.parametrize("event", list(Event))
def test_every_event_round_trips(event: Event) -> None:
    reply_to = "peer-7" if event is Event.ACK else None
    sent = make(event, SAMPLES[event], reply_to=reply_to, id="abc-1", now=12.5)
    text = encode(sent)
    assert text == json.dumps(json.loads(text), separators=(",", ":"))
    received = decode(text)
    assert received == sent
    assert received.event == event and received.kind is event
    assert parse_payload(received) == PAYLOADS[event].model_validate(SAMPLES[event])
    assert decode(text.encode()) == sent
    assert encode(received) == text


@pytest.mark.parametrize("event", list(Event))
def test_an_envelope_as_json_data_is_what_its_text_reads_as(event: Event) -> None:
    reply_to = "peer-7" if event is Event.ACK else None
    sent = make(event, SAMPLES[event], reply_to=reply_to, id="abc-1", now=12.5)
    assert protocol.as_json_data(sent) == json.loads(encode(sent))


def test_a_log_entry_as_json_data_writes_what_json_cannot_hold_as_its_text_does() -> None:
    data = {"value": float("inf"), "other": float("nan"), "text": "caf\u00e9 \U0001f916", "big": 2**70}
    entry = make(Event.LOG_EVENT, {**SAMPLES[Event.LOG_EVENT], "data": data}, now=12.5)
    assert protocol.as_json_data(entry) == json.loads(encode(entry))
    assert protocol.as_json_data(entry)["data"]["data"] == {
        "value": None,
        "other": None,
        "text": data["text"],
        "big": 2**70,
    }


@pytest.mark.parametrize("event", list(Event))
def test_raw_outside_frames_decode(event: Event) -> None:
    extra = {"reply_to": "peer-7"} if event is Event.ACK else {}
    envelope = decode(frame(event.value, SAMPLES[event], **extra).encode())
    assert isinstance(parse_payload(envelope), PAYLOADS[event])


def test_envelope_without_ts_and_reply_to_is_accepted() -> None:
    envelope = decode(b'{"event":"robot_config_get","id":"1","data":{}}')
    assert envelope.ts == 0.0 and envelope.reply_to is None


def test_pinned_metrics_shape_decodes() -> None:
    text = frame("metrics", {"metrics": [{"name": "cpu", "value": 1, "ts": 2, "labels": {"core": "0"}}]})
    payload = parse_payload(decode(text))
    assert isinstance(payload, MetricsPayload)
    assert payload.metrics[0] == {"name": "cpu", "value": 1.0, "ts": 2.0, "labels": {"core": "0"}}
    assert type(payload.metrics[0]) is dict  # a plain dict: the collector never walks it


@pytest.mark.parametrize(
    ("text", "code", "field"),
    [
        ("{not json", "invalid_json", None),
        (b"\xff\xfe", "invalid_json", None),
        ("", "invalid_json", None),
        ("[1, 2]", "not_object", None),
        ('"metrics"', "not_object", None),
        ("null", "not_object", None),
        ('{"id":"1","data":{}}', "invalid_envelope", "event"),
        ('{"event":"ack","data":{}}', "invalid_envelope", "id"),
        ('{"event":"metrics","id":"has space","data":{"metrics":[]}}', "invalid_envelope", "id"),
        ('{"event":"metrics","id":"' + "x" * 65 + '","data":{"metrics":[]}}', "invalid_envelope", "id"),
        ('{"event":"metrics","id":"1","data":[]}', "invalid_envelope", "data"),
        ('{"event":"metrics","id":"1","data":{"metrics":[]},"ts":"now"}', "invalid_envelope", "ts"),
        ('{"event":"metrics","id":"1","data":{"metrics":[]},"extra":1}', "invalid_envelope", "extra"),
        ('{"event":"ack","id":"1","data":{}}', "invalid_envelope", "reply_to"),
        ('{"event":"ack","id":"1","reply_to":"2","data":{"x":1}}', "invalid_payload", "data.x"),
        ('{"event":"reboot","id":"1","data":{}}', "unknown_event", "event"),
        ('{"event":"skill_connnect","id":"1","data":{"skill":"a"}}', "unknown_event", "event"),
        ('{"event":"skill_start","id":"1","data":{}}', "invalid_payload", "data.skill"),
        ('{"event":"skill_start","id":"1","data":{"skill":"Bad Slug"}}', "invalid_payload", "data.skill"),
        ('{"event":"skill_status","id":"1","data":{"skill":"a","status":"dancing"}}', "invalid_payload", "data.status"),
        (
            '{"event":"component_start","id":"1","data":{"skill":"a","component":"b","location":"either"}}',
            "invalid_payload",
            "data.location",
        ),
        ('{"event":"offloading","id":"1","data":{"mode":"sometimes"}}', "invalid_payload", "data.mode"),
        ('{"event":"authentication_robot","id":"1","data":{"robot":"r1"}}', "invalid_payload", "data.token"),
        (
            '{"event":"authentication_robot","id":"1","data":{"robot":"r1","token":"a b"}}',
            "invalid_payload",
            "data.token",
        ),
        (
            '{"event":"metrics","id":"1","data":{"metrics":[{"name":"cpu","value":"1","ts":1}]}}',
            "invalid_payload",
            "data.metrics.0.value",
        ),
        (
            '{"event":"metrics","id":"1","data":{"metrics":[{"name":"9cpu","value":1,"ts":1}]}}',
            "invalid_payload",
            "data.metrics.0.name",
        ),
        (
            '{"event":"metrics","id":"1","data":{"metrics":[{"name":"cpu","value":1,"ts":-1}]}}',
            "invalid_payload",
            "data.metrics.0.ts",
        ),
        ('{"event":"metrics_get","id":"1","data":{"limit":0}}', "invalid_payload", "data.limit"),
        (
            '{"event":"component_information","id":"1","data":{"skill":"a","component":"b","location":"robot",'
            '"container":{"ip":"999.1.1.1"}}}',
            "invalid_payload",
            "data.container.ip",
        ),
    ],
)
def test_bad_frame_is_rejected_naming_the_field(text: str | bytes, code: str, field: str | None) -> None:
    error = rejection(text)
    assert (error.code, error.field) == (code, field)
    assert str(error).startswith(f"{field}: ") if field else str(error)


def test_non_finite_metric_value_names_its_index() -> None:
    points = [{"name": "cpu", "value": 0.5, "ts": 1.0} for _ in range(5)]
    text = frame("metrics", {"metrics": points}).replace('"value": 0.5', '"value": NaN', 4)
    text = text.replace('"value": NaN', '"value": 0.5', 3)
    error = rejection(text)
    assert str(error) == "data.metrics.3.value: Input should be a finite number"


def test_three_n_skill_connnect_is_unknown() -> None:
    error = rejection(frame("skill_connnect", {"skill": "people-detector"}))
    assert error.code == "unknown_event"
    assert "skill_connnect" in str(error)
    with pytest.raises(ProtocolError):
        make("skill_connnect", {"skill": "a"}, now=0)


def test_oversize_frame_is_rejected_before_parsing() -> None:
    text = frame("robot_config", {"config": {"blob": "x" * 2000}})
    error = rejection(text, max_bytes=1000)
    assert error.code == "too_large" and "1000" in str(error)
    assert rejection(text.encode(), max_bytes=1000).code == "too_large"
    multibyte = frame("robot_config", {"config": {"blob": "é" * 600}})
    assert len(multibyte) < 1000 < len(multibyte.encode())
    assert rejection(multibyte, max_bytes=1000).code == "too_large"
    assert decode(multibyte, max_bytes=2000).event == "robot_config"


def test_too_many_metric_points_are_rejected() -> None:
    point = {"name": "c", "value": 1, "ts": 1}
    error = rejection(frame("metrics", {"metrics": [point] * 10_001}), max_bytes=10_000_000)
    assert error.field == "data.metrics" and error.code == "invalid_payload"
    assert decode(frame("metrics", {"metrics": [point] * 10_000}), max_bytes=10_000_000)


def test_direction_table_rejects_a_robot_ordering_itself() -> None:
    text = frame("robot_start", {})
    error = rejection(text, direction=Direction.ROBOT_TO_CLOUD)
    assert (error.code, error.field) == ("forbidden_event", "event")
    assert decode(text, direction=Direction.CLIENT_TO_CLOUD).event == Event.ROBOT_START
    assert not is_allowed("authentication_robot", Direction.CLIENT_TO_CLOUD)
    assert is_allowed(Event.METRICS, "robot_to_cloud")
    assert not is_allowed("skill_connnect", "robot_to_cloud")


def test_make_validates_and_fills_the_envelope() -> None:
    envelope = make(Event.SKILL_STOP, {"skill": "nav"}, now=5.0)
    assert envelope.ts == 5.0 and envelope.reply_to is None and envelope.data == {"skill": "nav"}
    assert make(Event.SKILL_STOP, {"skill": "nav"}, now=5.0).id != envelope.id
    with pytest.raises(ProtocolError) as caught:
        make(Event.SKILL_STOP, {"skill": "Nav!"}, now=0)
    assert caught.value.field == "data.skill"
    with pytest.raises(ProtocolError) as caught:
        make(Event.ACK, now=0)
    assert caught.value.field == "reply_to"


def test_id_generator_is_unique_and_valid() -> None:
    generator = IdGenerator()
    ids = {generator() for _ in range(10_000)}
    assert len(ids) == 10_000
    assert all(Envelope(event="ack", id=i, reply_to="x").id == i for i in list(ids)[:50])
    other = IdGenerator()
    assert other() != IdGenerator()()


def test_ack_and_error_frames() -> None:
    ack = decode(encode(ack_frame("abc-9", now=3.0)))
    assert ack.event == Event.ACK and ack.reply_to == "abc-9" and ack.data == {}
    error = rejection(frame("skill_start", {"skill": "UPPER"}))
    reply = decode(encode(error_frame(error, "m-1", now=4.0)))
    assert reply.event == Event.ERROR_MESSAGE and reply.reply_to == "m-1"
    assert reply.data["field"] == "data.skill" and reply.data["code"] == "invalid_payload"
    assert reply.data["message"].startswith("data.skill: ")
    assert error_frame(error, "not an id!", now=4.0).reply_to is None
    crash = decode(encode(error_frame(RuntimeError(""), None, now=4.0)))
    assert crash.data == {"message": "RuntimeError", "code": "internal_error"}


# --------------------------------------------------------------------------- reliability


def status(n: int) -> Envelope:
    return make(Event.SKILL_STATUS, {"skill": "nav", "status": "running"}, id=f"s-{n}", now=0)


def test_retransmission_backs_off_exponentially_up_to_the_cap() -> None:
    sender = Reliable(random=lambda: 0.5)
    envelope = status(1)
    assert sender.send(envelope, now=0.0)
    fired: list[float] = []
    now = 0.0
    while now <= 200.0:
        if sender.due(now):
            fired.append(now)
        now = round(now + 0.5, 1)
    gaps = [b - a for a, b in zip([0.0, *fired], fired, strict=False)]
    assert gaps[:7] == [1.0, 2.0, 4.0, 8.0, 16.0, 30.0, 30.0]
    assert sender.attempts("s-1") == len(fired) + 1
    assert sender.pending() == [envelope]


def test_ack_stops_retransmission() -> None:
    sender = Reliable(random=lambda: 0.5)
    sender.send(status(1), now=0.0)
    sender.send(status(2), now=0.0)
    assert [e.id for e in sender.due(1.0)] == ["s-1", "s-2"]
    assert sender.on_ack("s-1")
    assert not sender.on_ack("s-1")
    assert [e.id for e in sender.due(3.0)] == ["s-2"]
    assert sender.on_ack(decode(encode(ack_frame("s-2", now=3.0))).reply_to)
    assert sender.due(1000.0) == [] and sender.pending() == [] and sender.next_due() is None


def test_only_state_changing_events_are_tracked() -> None:
    sender = Reliable()
    assert not sender.send(make(Event.SKILL_STATUS_GET, {"skill": "nav"}, now=0), now=0)
    assert not sender.send(ack_frame("x", now=0), now=0)
    assert sender.send(make(Event.METRICS, {"metrics": []}, now=0), now=0)
    assert len(sender) == 1


def test_jitter_stays_within_bounds_and_cap() -> None:
    low, high = Reliable(random=lambda: 0.0), Reliable(random=lambda: 0.999999)
    low.send(status(1), now=0.0)
    high.send(status(1), now=0.0)
    assert low.next_due() == pytest.approx(0.9)
    assert high.next_due() == pytest.approx(1.1, abs=1e-5)
    for sender in (low, high):
        for _ in range(20):
            sender.due(sender.next_due() or 0.0)
        before = sender.next_due() or 0.0
        sender.due(before)
        assert (sender.next_due() or 0.0) - before <= 30.0


def test_resend_all_makes_everything_due_in_order() -> None:
    sender = Reliable(random=lambda: 0.5)
    for n in range(3):
        sender.send(status(n), now=float(n))
    assert [e.id for e in sender.resend_all(10.0)] == ["s-0", "s-1", "s-2"]
    assert sender.due(10.5) == []
    assert sender.next_due() == 12.0


def test_duplicate_event_is_applied_once() -> None:
    dedup = Dedup()
    applied = [frame_id for frame_id in ["a", "b", "a", "c", "b"] if not dedup.seen(frame_id)]
    assert applied == ["a", "b", "c"]


def test_dedup_window_is_bounded_lru() -> None:
    dedup = Dedup(capacity=3)
    for frame_id in "abc":
        dedup.seen(frame_id)
    assert dedup.seen("a")  # refreshes a, so b is now the oldest
    dedup.seen("d")
    assert len(dedup) == 3 and "b" not in dedup
    assert not dedup.seen("b")
    big = Dedup()
    for n in range(25_000):
        big.seen(str(n))
    assert len(big) == 10_000 and big.seen("24999") and not big.seen("0")


def test_dedup_survives_export_and_load() -> None:
    dedup = Dedup(capacity=5)
    for frame_id in "abcdefg":
        dedup.seen(frame_id)
    saved = json.loads(json.dumps(dedup.export()))
    assert saved == list("cdefg")
    restored = Dedup(capacity=5, ids=saved)
    assert restored.seen("g") and restored.seen("c") and not restored.seen("a")
    dedup.forget("g")
    assert not dedup.seen("g")


def test_correlator_matches_replies_and_expires_requests() -> None:
    correlator = Correlator()
    request = make(Event.SKILL_STATUS_GET, {"skill": "nav"}, id="q-1", now=0)
    correlator.expect(request.id, now=0.0, timeout=5.0)
    correlator.expect("q-2", now=1.0, timeout=5.0)
    reply = make(Event.SKILL_STATUS, {"skill": "nav", "status": "stopped"}, reply_to="q-1", now=1)
    assert correlator.resolve(decode(encode(reply)))
    assert not correlator.resolve(reply)
    assert not correlator.resolve(status(9))
    assert correlator.expired(5.9) == []
    assert correlator.expired(6.0) == ["q-2"]
    assert len(correlator) == 0
    correlator.expect("q-3", now=0.0, timeout=1.0)
    correlator.expect("q-3", now=0.0, timeout=10.0)
    assert correlator.expired(2.0) == [] and correlator.pending() == ["q-3"]


# --------------------------------------------------------------------------- fuzzing

json_values = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=20),
    lambda children: st.lists(children, max_size=4) | st.dictionaries(st.text(max_size=10), children, max_size=4),
    max_leaves=20,
)


def envelope_like() -> st.SearchStrategy[dict[str, Any]]:
    events = st.sampled_from([*(e.value for e in Event), "skill_connnect", ""]) | st.text(max_size=8)
    data = st.one_of(
        st.sampled_from(list(SAMPLES.values())),
        st.dictionaries(
            st.sampled_from(["skill", "component", "location", "metrics", "token", "robot", "mode", "status"]),
            json_values,
            max_size=4,
        ),
        json_values,
    )
    return st.fixed_dictionaries(
        {"event": events, "id": st.text(max_size=70) | json_values, "data": data},
        optional={"reply_to": st.none() | st.text(max_size=10), "ts": json_values},
    )


def decode_only_raises_protocol_error(text: str | bytes) -> None:
    try:
        envelope = decode(text)
    except ProtocolError as error:
        assert str(error) and error.code
        return
    assert decode(encode(envelope)) == envelope


@settings(max_examples=2000, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.text() | st.binary())
def test_random_text_and_bytes_only_raise_protocol_error(text: str | bytes) -> None:
    decode_only_raises_protocol_error(text)


@settings(max_examples=2000, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(json_values | envelope_like())
def test_random_json_only_raises_protocol_error(value: Any) -> None:
    decode_only_raises_protocol_error(json.dumps(value))
    decode_only_raises_protocol_error(json.dumps(value).encode())


def test_module_imports_no_io_or_clock() -> None:
    tree = ast.parse(Path(protocol.__file__).read_text(encoding="utf-8"))
    imported = {
        alias.name.split(".")[0] for node in ast.walk(tree) if isinstance(node, ast.Import) for alias in node.names
    }
    imported |= {
        node.module.split(".")[0] for node in ast.walk(tree) if isinstance(node, ast.ImportFrom) and node.module
    }
    assert not imported & {"time", "datetime", "asyncio", "socket", "threading", "websockets", "channels"}

"""Robot labels and selectors as pure functions: the rules of a label, the `k=v` text, selectors and matching."""

from __future__ import annotations

import pytest
from django.contrib.auth import get_user_model
from django.core.exceptions import ValidationError

from bridgeos_agent.labels import LabelError, label_problems
from bridgeos_agent.labels import parse_labels as agent_parse_labels
from robots.labels import Selector, Term, matches, parse_labels, parse_selector, selector_q, validate_labels
from robots.models import Robot
from robots.services import create_robot

GOOD_LABELS = [
    {},
    {"site": "lab"},
    {"site": "Lab-1", "model": "turtlebot3.burger", "gpu": ""},
    {"a": "b"},
    {"k8s.io_x-y": "V_1.2-x"},
    {"x" * 63: "y" * 63},
    {f"k{i}": str(i) for i in range(64)},
]


@pytest.mark.parametrize("labels", GOOD_LABELS)
def test_valid_labels_pass_unchanged(labels):
    assert label_problems(labels) == []
    assert validate_labels(labels) == labels


@pytest.mark.parametrize(
    ("labels", "named"),
    [
        ({"Site": "lab"}, "'Site'"),  # keys are lowercase
        ({"-site": "lab"}, "'-site'"),
        ({"site-": "lab"}, "'site-'"),
        ({"": "lab"}, "''"),
        ({"si te": "lab"}, "'si te'"),
        ({"site/x": "lab"}, "'site/x'"),
        ({"x" * 64: "v"}, "'" + "x" * 64 + "'"),
        ({"site": "-lab"}, "'site'"),
        ({"site": "lab "}, "'site'"),
        ({"site": "a,b"}, "'site'"),
        ({"site": "a=b"}, "'site'"),
        ({"site": "y" * 64}, "'site'"),
        ({"site": 1}, "'site'"),
        ({"site": None}, "'site'"),
        ({"ok": "x", "Bad": "y"}, "'Bad'"),
    ],
)
def test_a_bad_label_is_refused_naming_its_key(labels, named):
    problems = label_problems(labels)
    assert len(problems) == 1 and named in problems[0], problems
    with pytest.raises(ValidationError) as caught:
        validate_labels(labels)
    assert named in caught.value.message_dict["labels"][0]


def test_more_than_64_labels_are_refused():
    problems = label_problems({f"k{i}": "v" for i in range(65)})
    assert problems == ["at most 64 labels, not 65"]


@pytest.mark.parametrize("labels", [["site=lab"], "site=lab", None, 3])
def test_labels_must_be_an_object(labels):
    assert label_problems(labels) == ["labels must be an object of key: value strings"]


@pytest.mark.parametrize(
    ("text", "labels"),
    [
        ("", {}),
        ("  ", {}),
        ("site=lab", {"site": "lab"}),
        ("site=lab,model=turtlebot", {"site": "lab", "model": "turtlebot"}),
        (" site = lab , gpu= ", {"site": "lab", "gpu": ""}),
        ("site=lab,site=lab", {"site": "lab"}),
    ],
)
def test_label_text_parses(text, labels):
    assert parse_labels(text) == labels
    assert agent_parse_labels(text) == labels


def test_several_label_texts_merge_as_repeated_flags_do():
    assert agent_parse_labels(["site=lab", "model=x,arm=ur5"]) == {"site": "lab", "model": "x", "arm": "ur5"}


@pytest.mark.parametrize(
    ("text", "said"),
    [
        ("site", "label 'site' has no '='"),
        ("site=lab,,model=x", "label '' has no '='"),
        ("site=lab,site=field", "label 'site' is given twice"),
        ("Site=lab", "label key 'Site' is invalid"),
        ("site=la b", "label 'site': value 'la b' is invalid"),
        ("site=a=b", "label 'site': value 'a=b' is invalid"),
    ],
)
def test_bad_label_text_is_refused_naming_the_pair(text, said):
    with pytest.raises(LabelError, match=said):
        agent_parse_labels(text)
    with pytest.raises(ValidationError) as caught:
        parse_labels(text)
    assert said in caught.value.message_dict["labels"][0]


# --------------------------------------------------------------------------- selectors


@pytest.mark.parametrize(
    ("text", "terms"),
    [
        ("site=lab", [Term("=", "site", "lab")]),
        ("site=lab,model=turtlebot", [Term("=", "site", "lab"), Term("=", "model", "turtlebot")]),
        ("site!=lab", [Term("!=", "site", "lab")]),
        ("gpu", [Term("has", "gpu")]),
        ("!retired", [Term("lacks", "retired")]),
        (" site = lab , ! retired ,gpu", [Term("=", "site", "lab"), Term("lacks", "retired"), Term("has", "gpu")]),
        ("gpu=", [Term("=", "gpu", "")]),
        ("gpu!=", [Term("!=", "gpu", "")]),
    ],
)
def test_selectors_parse_into_terms(text, terms):
    selector = parse_selector(text)
    assert list(selector.terms) == terms
    assert parse_selector(str(selector)) == selector


@pytest.mark.parametrize(
    ("text", "term"),
    [
        ("Site=lab", "'Site=lab'"),
        ("site=lab,Model=x", "'Model=x'"),
        ("site=lab,", "''"),
        ("site==lab", "'site==lab'"),
        ("site=a=b", "'site=a=b'"),
        ("site=la b", "'site=la b'"),
        ("!", "'!'"),
        ("!site=lab", "'!site=lab'"),
        ("=lab", "'=lab'"),
        ("site!=-x", "'site!=-x'"),
    ],
)
def test_a_bad_selector_is_refused_naming_the_term(text, term):
    with pytest.raises(ValidationError) as caught:
        parse_selector(text)
    message = caught.value.message_dict["selector"][0]
    assert message.startswith(f"selector term {term} is invalid"), message


@pytest.mark.parametrize("text", ["", "   "])
def test_an_empty_selector_is_refused(text):
    with pytest.raises(ValidationError) as caught:
        parse_selector(text)
    assert "at least one term" in caught.value.message_dict["selector"][0]


FLEET = {
    "a": {"site": "lab", "model": "turtlebot", "k8s.io_x-y": "1"},
    "b": {"site": "lab", "model": "jackal", "gpu": ""},
    "c": {"site": "field", "model": "turtlebot", "retired": "yes"},
    "d": {},
    "e": {"model": "turtlebot"},
}
CASES = [
    ("site=lab", {"a", "b"}),
    ("site=lab,model=turtlebot", {"a"}),
    ("model=turtlebot", {"a", "c", "e"}),
    ("site!=lab", {"c", "d", "e"}),
    ("site", {"a", "b", "c"}),
    ("!site", {"d", "e"}),
    ("gpu", {"b"}),
    ("gpu=", {"b"}),
    ("!retired,model=turtlebot", {"a", "e"}),
    ("site=lab,site=field", set()),
    ("site=lab,site=lab", {"a", "b"}),
    ("site=lab,site!=lab", set()),
    ("model!=turtlebot,!gpu", {"d"}),
    ("nothing=here", set()),
    ("k8s.io_x-y=1", {"a"}),
    ("k8s.io_x-y!=1,site=lab", {"b"}),
]


@pytest.mark.parametrize(("text", "expected"), CASES)
def test_matches_picks_the_robots_whose_labels_meet_every_term(text, expected):
    assert {robot for robot, labels in FLEET.items() if matches(labels, text)} == expected
    assert {robot for robot, labels in FLEET.items() if matches(labels, parse_selector(text))} == expected


@pytest.mark.django_db
@pytest.mark.parametrize("containment", [True, False], ids=["containment", "key-text"])
def test_the_database_query_of_a_selector_finds_what_matches_finds(containment):
    # Without containment is the embedded SQLite's query; PostgreSQL runs it just as well, so both are checked here.
    owner = get_user_model().objects.create_user("labeller")
    for robot_id, labels in FLEET.items():
        create_robot(f"bot-{robot_id}", owner, labels=labels)
    for text, expected in CASES:
        found = set(Robot.objects.filter(selector_q(text, containment=containment)).values_list("id", flat=True))
        assert found == {f"bot-{robot}" for robot in expected}, text


def test_an_equality_selector_is_one_containment_query_a_gin_index_serves():
    sql = str(Robot.objects.filter(selector_q("site=lab,model=x")).query)
    assert sql.count("@>") == 1, sql


def test_a_selector_is_rendered_back_as_its_text():
    assert str(Selector((Term("=", "a", "b"), Term("!=", "c", "d"), Term("has", "e"), Term("lacks", "f")))) == (
        "a=b,c!=d,e,!f"
    )

"""Subnet allocation: from the pools, never overlapping (even past the application), freed with the robot."""

from __future__ import annotations

import ipaddress
from concurrent.futures import ThreadPoolExecutor

import pytest
from django.contrib.auth import get_user_model
from django.core.exceptions import ValidationError
from django.db import IntegrityError, connection, transaction
from django.test.utils import CaptureQueriesContext
from hypothesis import given, settings
from hypothesis import strategies as st

from network.ipam import first_free, subnets
from network.models import Subnet
from robots.models import Robot
from robots.services import create_robot, delete_robot, update_robot


def test_first_free_skips_taken_networks_and_aligns_to_the_prefix():
    assert first_free(["10.64.0.0/16"], [], 24) == "10.64.0.0/24"
    assert first_free(["10.64.0.0/16"], ["10.64.0.0/24", "10.64.1.128/25"], 24) == "10.64.2.0/24"
    assert first_free(["10.64.0.0/16"], ["10.64.0.7/32"], 24) == "10.64.1.0/24"
    assert first_free(["10.64.0.0/23", "10.65.0.0/24"], ["10.64.0.0/23"], 24) == "10.65.0.0/24"
    assert first_free(["10.64.0.0/24"], ["10.0.0.0/8"], 24) is None


@settings(max_examples=200, deadline=None)
@given(
    taken=st.lists(st.tuples(st.integers(0, 255), st.integers(16, 30)), max_size=12),
    prefix=st.integers(20, 28),
)
def test_first_free_never_overlaps_anything_taken(taken, prefix):
    pool = ipaddress.ip_network("10.64.0.0/16")
    nets = [str(ipaddress.ip_network((int(pool.network_address) + (n << 8), p), strict=False)) for n, p in taken]
    found = first_free([str(pool)], nets, prefix)
    if found is None:
        # Then truly no aligned network of that size is free.
        for candidate in pool.subnets(new_prefix=prefix):
            assert any(candidate.overlaps(ipaddress.ip_network(t)) for t in nets)
        return
    network = ipaddress.ip_network(found)
    assert network.prefixlen == prefix and network.subnet_of(pool)
    assert not any(network.overlaps(ipaddress.ip_network(t)) for t in nets)


@pytest.fixture
def owner(db):
    return get_user_model().objects.create_user("owner")


def nets(robot_id: str) -> dict[str, str]:
    return dict(Subnet.objects.filter(robot_id=robot_id).values_list("kind", "network"))


def test_a_new_robot_gets_disjoint_subnets_in_its_config(owner):
    first, _ = create_robot("r1", owner)
    create_robot("r2", owner)
    a, b = nets("r1"), nets("r2")
    assert Robot.objects.get(id="r1").config["subnets"] == {"local": a["local"], "cloud": a["cloud"]}
    assert subnets(first) == (a["local"], a["cloud"])
    everything = [ipaddress.ip_network(n) for n in [*a.values(), *b.values()]]
    assert all(not x.overlaps(y) for i, x in enumerate(everything) for y in everything[i + 1 :])
    assert ipaddress.ip_network(a["tunnel"]).prefixlen == 32


def test_deleting_a_robot_frees_its_subnets(owner):
    robot, _ = create_robot("r1", owner)
    freed = nets("r1")
    delete_robot(robot)
    assert not Subnet.objects.exists()
    create_robot("r2", owner)
    assert nets("r2") == freed


def test_an_operator_may_pick_free_subnets_inside_the_pools(owner):
    robot, _ = create_robot("r1", owner, config={"subnets": {"local": "10.64.9.0/24", "cloud": "10.80.9.0/24"}})
    assert nets("r1")["local"] == "10.64.9.0/24"
    update_robot(robot, config={**robot.config, "subnets": {"local": "10.64.10.0/24", "cloud": "10.80.9.0/24"}})
    assert nets("r1")["local"] == "10.64.10.0/24"
    from monitoring.models import Event

    assert Event.objects.filter(robot_id="r1", kind="robot_subnets", data__local="10.64.10.0/24").exists()


@pytest.mark.parametrize(
    ("subnets_", "message"),
    [
        ({"local": "10.64.0.0/24", "cloud": "10.80.7.0/24"}, "overlaps 10.64.0.0/24 of robot r1"),
        ({"local": "192.168.1.0/24", "cloud": "10.80.7.0/24"}, "outside the local pools"),
        ({"local": "10.64.7.0/24", "cloud": "10.64.8.0/24"}, "outside the cloud pools"),
    ],
)
def test_bad_subnets_are_refused_and_change_nothing(owner, subnets_, message):
    create_robot("r1", owner)
    before = list(Subnet.objects.order_by("id").values_list("robot_id", "kind", "network"))
    with pytest.raises(ValidationError, match=message):
        create_robot("r2", owner, config={"subnets": subnets_})
    assert not Robot.objects.filter(id="r2").exists()
    assert list(Subnet.objects.order_by("id").values_list("robot_id", "kind", "network")) == before


def test_a_robot_whose_subnets_are_allocated_as_configured_is_answered_without_the_allocation_lock(owner):
    robot, _ = create_robot("r1", owner)
    allocated = nets("r1")
    with CaptureQueriesContext(connection) as queries:
        assert subnets(robot) == (allocated["local"], allocated["cloud"])
    # One read: no lock every robot's cloud starts would queue on.
    assert len(queries) == 1 and "advisory" not in queries[0]["sql"]
    # A config asking for other subnets takes the locked way and moves them.
    robot.config = {**robot.config, "subnets": {"local": "10.64.77.0/24", "cloud": allocated["cloud"]}}
    with CaptureQueriesContext(connection) as queries:
        assert subnets(robot) == ("10.64.77.0/24", allocated["cloud"])
    assert any("pg_advisory_xact_lock" in q["sql"] for q in queries)


def test_a_config_without_subnets_keeps_the_allocated_ones(owner):
    robot, _ = create_robot("r1", owner)
    allocated = nets("r1")
    update_robot(robot, config={"heuristic": "migration_cost"})
    assert Robot.objects.get(id="r1").config["subnets"]["local"] == allocated["local"]
    assert nets("r1") == allocated


def test_postgresql_refuses_overlapping_rows_whatever_the_application_does(owner):
    if connection.vendor != "postgresql":
        pytest.skip("the exclusion constraint is PostgreSQL's")
    robot, _ = create_robot("r1", owner)
    other, _ = create_robot("r2", owner)
    with pytest.raises(IntegrityError), transaction.atomic():
        Subnet.objects.filter(robot=other, kind="local").update(network=nets("r1")["local"].replace("/24", "/25"))
    assert robot.pk


@pytest.mark.django_db(transaction=True)
def test_robots_created_at_once_never_share_a_subnet():
    owner = get_user_model().objects.create_user("owner")

    def make(n: int) -> None:
        from django.db import connection as thread_connection

        try:
            create_robot(f"par-{n}", owner)
        finally:
            thread_connection.close()

    with ThreadPoolExecutor(8) as pool:
        list(pool.map(make, range(16)))
    allocated = [ipaddress.ip_network(n) for n in Subnet.objects.values_list("network", flat=True)]
    assert len(allocated) == 48
    assert all(not x.overlaps(y) for i, x in enumerate(allocated) for y in allocated[i + 1 :])

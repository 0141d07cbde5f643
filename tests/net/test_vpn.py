"""Robots join the VPN, reach their own cloud subnet only, are refused once revoked, and fall back to WSS.

Everything is real: network namespaces joined by veth links, OpenVPN 2.6 (server from
`manage.py vpn run`, clients started by the agent), nftables on both sides, daphne serving
WSS with a certificate of the cloud's PKI, and TCP connections that prove who reaches whom.
"""

from __future__ import annotations

import os
import signal
import sqlite3
from collections.abc import Iterator

import pytest
from django.conf import settings
from django.contrib.auth import get_user_model

from monitoring.models import Metric
from network.models import Subnet
from robots.rotation import rotate_token
from robots.services import create_robot
from tests.net import netns
from tests.net.world import DEVICE, World, connects, network_settings, wait_until

why_not = netns.available()
pytestmark = [
    pytest.mark.django_db(transaction=True),
    pytest.mark.timeout(180),
    pytest.mark.skipif(why_not is not None, reason=f"VPN tests: {why_not}"),
]


@pytest.fixture
def world(monkeypatch: pytest.MonkeyPatch) -> Iterator[World]:
    monkeypatch.setattr(settings, "BRIDGEOS_NETWORK", network_settings(settings.BRIDGEOS_NETWORK))
    built = World(settings.DATABASES["default"]["NAME"])
    try:
        yield built
    finally:
        built.close()


def make_robot(world: World, robot_id: str, *, vpn: bool = True):
    owner, _ = get_user_model().objects.get_or_create(username="operator")
    robot, token = create_robot(robot_id, owner, config={"vpn": {"enabled": vpn}})
    nets = dict(Subnet.objects.filter(robot=robot).values_list("kind", "network"))
    return world.add_robot(robot_id, token, nets["local"], nets["cloud"])


def path_of(robot_id: str) -> float | None:
    """Return the latest path the robot reported: 1.0 through the VPN, 0.0 direct."""
    point = Metric.objects.filter(robot_id=robot_id, name="vpn").order_by("-ts", "-id").first()
    return None if point is None else point.value


def test_robots_reach_their_own_cloud_subnet_and_never_each_other(world):
    a, b = make_robot(world, "robot-a"), make_robot(world, "robot-b")
    world.start_cloud()
    for host in (a, b):
        world.agent(host)
    for host in (a, b):
        wait_until(lambda host=host: path_of(host.robot) == 1.0, f"{host.robot} over the VPN")
        assert "firewall: robot rules applied" in world.log(f"agent-{host.robot}.log")

    # Each robot, and its local containers, reach its own cloud subnet; the cloud side reaches back.
    for host in (a, b):
        for source, target, what in (
            (host.ns, host.cloud_host, "the robot reaches its cloud subnet"),
            (host.local_ns, host.cloud_host, "its local containers reach its cloud subnet"),
            (host.cloud_ns, host.local_host, "its cloud subnet reaches its local containers"),
        ):
            wait_until(lambda s=source, t=target: connects(s, t, 7000), f"{host.robot}: {what}", timeout=30)

    # Robot A turns rogue: it drops its own firewall and routes both pools into the tunnel.
    world.net.exec(a.ns, "nft", "delete", "table", "inet", "bridgeos")
    for pool in (*settings.BRIDGEOS_NETWORK["LOCAL_POOLS"], *settings.BRIDGEOS_NETWORK["CLOUD_POOLS"]):
        world.net.exec(a.ns, "ip", "route", "replace", pool, "dev", DEVICE)
    for source in (a.ns, a.local_ns):
        for target in (b.cloud_host, b.local_host):
            assert not connects(source, target, 7000), f"{source} reached robot B at {target}"
    assert not connects(a.cloud_ns, b.local_host, 7000), "robot A's cloud subnet reached robot B"
    assert not connects(b.cloud_ns, a.local_host, 7000), "robot B's cloud subnet reached robot A"
    # Its own paths still work: the cloud's rules, not a broken tunnel, stopped it.
    wait_until(lambda: connects(a.local_ns, a.cloud_host, 7000), "robot A still reaching its own cloud subnet")


def test_a_revoked_certificate_is_refused(world):
    host = make_robot(world, "robot-r")
    world.start_cloud()
    world.agent(host)
    wait_until(lambda: path_of(host.robot) == 1.0, "the robot over the VPN")
    profile = (world.dir / f"agent-{host.robot}" / "vpn" / "client.ovpn").read_text()

    from robots.models import Robot

    rotate_token(Robot.objects.get(id=host.robot))  # new credentials: the old certificate is revoked
    wait_until(lambda: "kill robot-r" in world.log("vpn.log"), "the server to cut the revoked tunnel")
    wait_until(lambda: path_of(host.robot) != 1.0 or host.processes[0].poll() is not None, "the tunnel to drop")

    # The old profile (certificate) no longer opens a tunnel.
    (world.dir / "old.ovpn").write_text(profile)
    client = world.spawn(
        host.ns,
        ["openvpn", "--config", str(world.dir / "old.ovpn"), "--dev", "bosnet-old", "--connect-retry-max", "1"],
        "old-client.log",
    )
    wait_until(
        lambda: "certificate revoked" in world.log("vpn/openvpn.log"), "the server to refuse the old certificate"
    )
    assert "Initialization Sequence Completed" not in world.log("old-client.log")
    client.terminate()


def outbox_pending(world: World, robot_id: str) -> int:
    path = world.dir / f"agent-{robot_id}" / "outbox.sqlite3"
    with sqlite3.connect(path, timeout=10) as db:
        return db.execute("SELECT count(*) FROM outbox").fetchone()[0]


def test_the_agent_falls_back_to_wss_without_losing_data_and_returns_to_the_vpn(world):
    host = make_robot(world, "robot-f")
    world.start_cloud()
    agent = world.agent(host, module="tests.net.seqrobot")
    wait_until(lambda: path_of(host.robot) == 1.0, "the robot over the VPN")

    world.stop_vpn()
    wait_until(lambda: path_of(host.robot) == 0.0, "the robot over WSS once the VPN is gone")
    seen = Metric.objects.filter(robot_id=host.robot, name="seq").count()
    wait_until(lambda: Metric.objects.filter(robot_id=host.robot, name="seq").count() > seen + 20, "data over WSS")

    world.start_vpn()
    wait_until(lambda: path_of(host.robot) == 1.0, "the robot back on the VPN")

    agent.send_signal(signal.SIGTERM)  # the helper stops counting, waits for every ack, then exits
    assert agent.wait(60) == 0, world.log(f"agent-{host.robot}.log")[-3000:]
    assert outbox_pending(world, host.robot) == 0
    values = sorted(
        int(v) for v in Metric.objects.filter(robot_id=host.robot, name="seq").values_list("value", flat=True)
    )
    assert set(values) == set(range(values[-1] + 1)), "a counted value is missing"
    # Frames in flight when the tunnel died come again over the new path; the cloud applies each once,
    # even one whose first copy was still being written when its copy arrived.
    assert len(values) == len(set(values)), f"{len(values) - len(set(values))} values stored twice"
    assert len(values) > 50
    paths = list(Metric.objects.filter(robot_id=host.robot, name="vpn").order_by("ts").values_list("value", flat=True))
    # Direct until the tunnel is up, then VPN, WSS while the VPN is gone, and the VPN again.
    assert [p for i, p in enumerate(paths) if i == 0 or p != paths[i - 1]][-3:] == [1.0, 0.0, 1.0], paths
    assert os.path.exists(world.dir / f"agent-{host.robot}" / "firewall.nft")

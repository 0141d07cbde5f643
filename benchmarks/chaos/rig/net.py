"""A robot's own network namespace, joined to this machine by one veth pair a scenario can cut and restore."""

from __future__ import annotations

import os

from tests.net.netns import Network, run


class RobotLink:
    """A robot's network namespace joined to this machine by one veth pair it can cut and restore."""

    def __init__(self) -> None:
        self.net = Network()
        self.namespace = self.net.host("robot")
        subnet = _free_subnet()
        self.cloud_address, self.robot_address = f"10.254.{subnet}.1", f"10.254.{subnet}.2"
        self.outside, self.inside = f"bc{self.net.tag}o"[:15], f"bc{self.net.tag}i"[:15]
        run("ip", "link", "add", self.outside, "type", "veth", "peer", "name", self.inside, "netns", self.namespace)
        run("ip", "addr", "add", f"{self.cloud_address}/30", "dev", self.outside)
        run("ip", "link", "set", self.outside, "up")
        self.net.exec(self.namespace, "ip", "addr", "add", f"{self.robot_address}/30", "dev", self.inside)
        self.net.exec(self.namespace, "ip", "link", "set", self.inside, "up")

    def cut(self) -> None:
        """Take the robot's end of the link down: nothing passes, no socket is told."""
        self.net.exec(self.namespace, "ip", "link", "set", self.inside, "down")

    def restore(self) -> None:
        self.net.exec(self.namespace, "ip", "link", "set", self.inside, "up")

    def close(self) -> None:
        run("ip", "link", "del", self.outside, check=False)
        self.net.close()


def _free_subnet() -> int:
    """Pick a 10.254.N.0/30 no interface of this machine uses."""
    used = run("ip", "-4", "-o", "addr", "show").stdout
    for n in range(os.getpid() % 200 + 20, 255):
        if f"10.254.{n}." not in used:
            return n
    raise RuntimeError("no free 10.254.N.0/30 for the robot's link")

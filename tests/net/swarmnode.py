"""A second Swarm node: an engine of its own in a network namespace, linked to this machine, joined as a worker.

While it is up, Swarm would place any new task of this machine (another test's, another
session's) on it first, as the emptiest node, where its image is missing. So the node is
*paused* (no new tasks) except inside :meth:`SwarmNode.accepting`, which a test holds only while
its own constrained task is being placed.

The namespace reaches this machine over one veth pair (a /30: this machine's end is
``host_address``, the node's ``address``); a registry listening on ``host_address`` is what the
node pulls from, so every byte it pulls crosses that link. The node starts with an empty image
store. Closing leaves the Swarm, removes the node from the manager's list (a left node would
stay "Down" there), stops the engine and deletes the namespace and its link.
"""

from __future__ import annotations

import contextlib
import ipaddress
import os
from collections.abc import Iterator
from dataclasses import dataclass

from tests.net.engine import Engine
from tests.net.netns import Network, run

# Link addresses are taken from here, a /30 per node, skipping any this machine already uses.
POOL = ipaddress.ip_network("10.251.0.0/16")


@dataclass
class SwarmNode:
    """A worker node of this machine's Swarm, in its own namespace behind one link."""

    engine: Engine
    network: Network
    namespace: str
    host_address: str  # this machine's end of the link: where the node finds registries
    address: str  # the node's end: its Swarm advertise address
    link: str  # this machine's interface of the link, to shape or count its traffic

    @property
    def node_id(self) -> str:
        return self.engine.node_id

    def availability(self, state: str) -> None:
        """Set the node's availability: ``active`` (takes new tasks) or ``pause`` (keeps what it runs)."""
        run("docker", "node", "update", "--availability", state, self.node_id)

    @contextlib.contextmanager
    def accepting(self) -> Iterator[None]:
        """Let Swarm place new tasks on the node while the block runs; keep them there afterwards."""
        self.availability("active")
        try:
            yield
        finally:
            self.availability("pause")


def _free_subnet() -> ipaddress.IPv4Network:
    """Return a /30 of POOL that no interface here is on, starting from one derived from this process's pid."""
    used = [
        ipaddress.ip_interface(word).network
        for line in run("ip", "-4", "-o", "addr", "show").stdout.splitlines()
        for word in line.split()[3:4]
    ]
    subnets = list(POOL.subnets(new_prefix=30))
    start = os.getpid() % len(subnets)
    for offset in range(len(subnets)):
        candidate = subnets[(start + offset) % len(subnets)]
        if not any(candidate.overlaps(network) for network in used):
            return candidate
    raise RuntimeError(f"no free /30 left in {POOL}")


@contextlib.contextmanager
def swarm_node(name: str = "node") -> Iterator[SwarmNode]:
    """Start a worker node in a namespace linked to this machine; remove everything of it afterwards."""
    network = Network()
    engine: Engine | None = None
    try:
        namespace = network.host(name)
        subnet = _free_subnet()
        host_address, address = (str(ip) for ip in list(subnet.hosts())[:2])
        # The host end lives in this machine's namespace; deleting the namespace deletes the pair.
        host_end, node_end = f"bn{network.tag}{name[:3]}h", f"bn{network.tag}{name[:3]}n"
        run("ip", "link", "add", host_end, "type", "veth", "peer", "name", node_end, "netns", namespace)
        run("ip", "addr", "add", f"{host_address}/30", "dev", host_end)
        run("ip", "link", "set", host_end, "up")
        network.exec(namespace, "ip", "addr", "add", f"{address}/30", "dev", node_end)
        network.exec(namespace, "ip", "link", "set", node_end, "up")
        network.exec(namespace, "ip", "route", "add", "default", "via", host_address)
        engine = Engine(namespace, name, address=address).start()
        engine.join_swarm()
        node = SwarmNode(engine, network, namespace, host_address, address, host_end)
        node.availability("pause")
        yield node
    finally:
        if engine is not None:
            engine.close()
        network.close()

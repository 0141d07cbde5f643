"""The robot's bridge doors: WebSocket servers feeding each connection to a rosbridge or Foxglove session."""

from __future__ import annotations

import asyncio
import contextlib
import functools
import logging
import os
from collections.abc import Sequence
from typing import Any

from websockets.asyncio.server import Server, ServerConnection, serve
from websockets.exceptions import ConnectionClosed
from websockets.typing import Subprotocol

from bridgeos_agent.bridges.foxglove import MAX_FRAME_BYTES as FOXGLOVE_MAX_FRAME_BYTES
from bridgeos_agent.bridges.foxglove import SUBPROTOCOLS, Foxglove, select_subprotocol
from bridgeos_agent.bridges.graph import BridgeGraph
from bridgeos_agent.bridges.rosbridge import MAX_FRAME_BYTES, Rosbridge

__all__ = ["FoxgloveServer", "RosbridgeServer", "open_graph", "parse_address"]

logger = logging.getLogger(__name__)


def parse_address(text: str) -> tuple[str, int]:
    """Split HOST:PORT (IPv6 as [::1]:PORT), raising ValueError with the reason."""
    from bridgeos_agent.metrics import parse_address as split

    return split(text)


class _Door:
    """A WebSocket server feeding each connection to a session of one protocol engine."""

    subprotocols: tuple[str, ...] | None = None

    def __init__(self, graph: BridgeGraph, bridge: Rosbridge | Foxglove, max_frame_bytes: int) -> None:
        self.graph = graph
        self.bridge = bridge
        self.max_frame_bytes = max_frame_bytes
        self._server: Server | None = None
        self.port = 0

    async def start(self, host: str, port: int) -> None:
        """Listen (port 0 picks a free one; ``port`` tells which)."""
        self._server = await serve(
            self._connection,
            host,
            port,
            # Frames up to 4x the protocol's limit reach the session, which refuses them with a status and
            # keeps the connection; only beyond that does the socket close (1009), so memory stays bounded.
            max_size=self.max_frame_bytes * 4,
            compression=None,
            subprotocols=[Subprotocol(name) for name in self.subprotocols or ()] or None,
            select_subprotocol=self._select if self.subprotocols else None,
        )
        self.port = next(iter(self._server.sockets)).getsockname()[1]

    @staticmethod
    def _select(connection: ServerConnection, offered: Sequence[str]) -> Subprotocol | None:
        chosen = select_subprotocol(offered)
        return Subprotocol(chosen) if chosen else None

    async def _connection(self, websocket: ServerConnection) -> None:
        session = self.bridge.session(websocket.send, functools.partial(send_frames, websocket))
        writer = asyncio.get_running_loop().create_task(session.run())
        try:
            async for frame in websocket:
                await session.receive(frame)
        except ConnectionClosed:
            pass
        finally:
            writer.cancel()
            with contextlib.suppress(asyncio.CancelledError, ConnectionClosed):
                await writer
            await session.close()

    async def close(self) -> None:
        """Stop listening, end every session and leave the graph."""
        if self._server is not None:
            self._server.close()
            await self._server.wait_closed()
            self._server = None
        await self.bridge.close()
        await self.graph.close()


async def send_frames(websocket: ServerConnection, frames: list[str | bytes]) -> None:
    """Send several frames with one socket write.

    ``send`` writes each frame on its own (a system call and a send context each): at ten thousand
    small messages a second that is a third of a door's time. This is the pattern websockets
    documents for ``send_context``, with the frames' bytes joined before they reach the socket.
    """
    if len(frames) == 1:
        await websocket.send(frames[0])
        return
    async with websocket.send_context():
        protocol = websocket.protocol
        for frame in frames:
            if isinstance(frame, str):
                protocol.send_text(frame.encode())
            else:
                protocol.send_binary(frame)
        websocket.transport.write(b"".join(protocol.data_to_send()))


class RosbridgeServer(_Door):
    """Serve rosbridge v2 on HOST:PORT for one graph; unauthenticated, like rosbridge_server."""

    bridge: Rosbridge

    def __init__(self, graph: BridgeGraph, *, max_frame_bytes: int = MAX_FRAME_BYTES, **options: Any) -> None:
        super().__init__(graph, Rosbridge(graph, max_frame_bytes=max_frame_bytes, **options), max_frame_bytes)


class FoxgloveServer(_Door):
    """Serve the Foxglove WebSocket protocol on HOST:PORT for one graph; unauthenticated, like foxglove_bridge."""

    subprotocols = SUBPROTOCOLS
    bridge: Foxglove

    def __init__(self, graph: BridgeGraph, *, max_frame_bytes: int = FOXGLOVE_MAX_FRAME_BYTES, **options: Any) -> None:
        super().__init__(graph, Foxglove(graph, max_frame_bytes=max_frame_bytes, **options), max_frame_bytes)


async def open_graph(ros: str, name: str = "bridgeos_rosbridge") -> BridgeGraph:
    """Join the robot's ROS 1 graph (its ROS_MASTER_URI) or ROS 2 graph (its ROS 2 env) as node ``name``."""
    if ros == "ros1":
        from bridgeos_agent.bridges.ros1graph import Ros1Graph
        from bridgeos_agent.rosmaster import DEFAULT_ROS_MASTER

        host = os.environ.get("ROS_IP") or os.environ.get("ROS_HOSTNAME") or "127.0.0.1"
        graph1 = Ros1Graph(os.environ.get("ROS_MASTER_URI") or DEFAULT_ROS_MASTER, name="/" + name, host=host)
        await graph1.start()
        return graph1
    from bridgeos_agent.bridges.ros2graph import Ros2BridgeGraph
    from bridgeos_agent.ros2graph import Ros2Graph

    graph2 = Ros2BridgeGraph(Ros2Graph.from_env(), asyncio.get_running_loop(), name=name)
    return graph2

"""Find a running ROS 1 master by asking it for its system state over XML-RPC."""

from __future__ import annotations

import http.client
import os
import xmlrpc.client
from typing import Any, cast
from urllib.parse import urlsplit

__all__ = ["DEFAULT_ROS_MASTER", "find_ros_master", "ros_master_answers"]

DEFAULT_ROS_MASTER = "http://127.0.0.1:11311"


class _TimeoutTransport(xmlrpc.client.Transport):
    """An XML-RPC transport whose connections give up after ``timeout`` seconds."""

    def __init__(self, timeout: float) -> None:
        super().__init__()
        self.timeout = timeout

    def make_connection(self, host: Any) -> http.client.HTTPConnection:
        connection = super().make_connection(host)
        connection.timeout = self.timeout
        return connection


def ros_master_answers(uri: str, *, timeout: float = 1.0) -> bool:
    """Tell whether a ROS master answers getSystemState at ``uri``."""
    parts = urlsplit(uri)
    if parts.scheme != "http" or not parts.hostname:
        return False
    proxy = xmlrpc.client.ServerProxy(uri, transport=_TimeoutTransport(timeout))
    try:
        # [code, status message, system state]; a reply of another shape raises ValueError.
        code, _, _ = cast(list[Any], proxy.getSystemState("/bridgeos_agent"))
    except (TimeoutError, OSError, xmlrpc.client.Error, ValueError):
        return False
    return code == 1


def find_ros_master(*, timeout: float = 1.0) -> str | None:
    """Return the URI of a local ROS master (ROS_MASTER_URI, else the default port), or None."""
    candidates = [os.environ.get("ROS_MASTER_URI"), DEFAULT_ROS_MASTER]
    for uri in dict.fromkeys(c for c in candidates if c):
        if ros_master_answers(uri, timeout=timeout):
            return uri
    return None

"""ROS 2 message definitions as text (``ros2msg``), read from the installed interface packages.

An interface package ships its ``.msg``/``.srv`` files in ``share/<package>/`` of its prefix (the
ROS 2 wheels install them under the interpreter's prefix; a sourced workspace lists its prefixes
in ``AMENT_PREFIX_PATH``). A full definition is the type's own text followed by each type inside
it, once, after a line of 80 '=' and a line 'MSG: pkg/msg/Type', as rosbag2 and foxglove_bridge
write it.
"""

from __future__ import annotations

import functools
import glob
import os
import sys
from pathlib import Path

from bridgeos_agent.bridges.graph import BridgeError

__all__ = ["SEPARATOR", "message_definition", "service_definitions"]

SEPARATOR = "=" * 80
_PRIMITIVES = {
    "bool",
    "byte",
    "char",
    "float32",
    "float64",
    "int8",
    "uint8",
    "int16",
    "uint16",
    "int32",
    "uint32",
    "int64",
    "uint64",
    "string",
    "wstring",
}


def _prefixes() -> list[Path]:
    roots = [Path(p) for p in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep) if p]
    roots += [Path(sys.prefix), *(Path(p) for p in sorted(glob.glob("/opt/ros/*")))]
    return list(dict.fromkeys(roots))


@functools.lru_cache(maxsize=1024)
def _text(package: str, kind: str, name: str) -> str:
    for prefix in _prefixes():
        path = prefix / "share" / package / kind / f"{name}.{kind}"
        if path.is_file():
            try:
                return path.read_text()
            except OSError:
                continue
    raise BridgeError(f"no definition of {package}/{kind}/{name} is installed ({kind} file not found)")


def _split(type_: str, kind: str) -> tuple[str, str]:
    parts = type_.strip("/").split("/")
    if len(parts) == 2:
        parts = [parts[0], kind, parts[1]]
    if len(parts) != 3 or parts[1] != kind or not all(p and p.replace("_", "").isalnum() for p in parts):
        raise BridgeError(f"{type_!r} is not a ROS 2 {kind} type ('package/{kind}/Type')")
    return parts[0], parts[2]


def _references(text: str, package: str) -> list[str]:
    """Return the message types the fields of a definition name, as 'pkg/msg/Type'."""
    found = []
    for line in text.splitlines():
        words = line.split("#", 1)[0].split()
        if len(words) < 2 or "=" in words[0]:
            continue
        base = words[0].split("[", 1)[0].split("<=", 1)[0]
        if base in _PRIMITIVES or "=" in words[1]:  # a primitive field, or a constant
            continue
        ref_package, _, short = base.rpartition("/")
        found.append(f"{ref_package or package}/msg/{short}")
    return found


def _complete(text: str, package: str) -> str:
    parts = [text.strip("\n")]
    seen: set[str] = set()
    queue = _references(text, package)
    while queue:
        name = queue.pop(0)
        if name in seen:
            continue
        seen.add(name)
        ref_package, short = _split(name, "msg")
        body = _text(ref_package, "msg", short)
        parts.append(f"{SEPARATOR}\nMSG: {name}\n{body.rstrip(chr(10))}")
        queue.extend(_references(body, ref_package))
    text = "\n".join(parts)
    return text + "\n" if text else ""


def message_definition(type_: str) -> str:
    """Return a message type's full ros2msg definition; raise BridgeError when its files are not installed."""
    package, short = _split(type_, "msg")
    return _complete(_text(package, "msg", short), package)


def service_definitions(type_: str) -> tuple[str, str]:
    """Return the full ros2msg definitions of a service type's request and response."""
    package, short = _split(type_, "srv")
    lines = _text(package, "srv", short).splitlines()
    cut = next((i for i, line in enumerate(lines) if line.strip() == "---"), len(lines))
    request, response = "\n".join(lines[:cut]), "\n".join(lines[cut + 1 :])
    return _complete(request, package), _complete(response, package)

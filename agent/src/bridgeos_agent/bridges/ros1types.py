"""ROS 1 messages as plain data and back, from their definitions, without rospy (rosbags does the wire format).

Where a definition comes from, first found wins: a publisher's connection header (learned as
topics are read), rosbags' built-in Noetic types, the genpy modules of the host's ROS python
(read as text, never imported), then ``.msg``/``.srv`` files on ``ROS_PACKAGE_PATH`` and the
usual share directories.
"""

from __future__ import annotations

import ast
import base64
import glob
import logging
import os
import sys
from pathlib import Path
from typing import Any

from bridgeos_agent.bridges.graph import BridgeError

__all__ = ["Ros1Types", "ros1_name"]

logger = logging.getLogger(__name__)

TIME_TYPES = {"builtin_interfaces/msg/Time": "time", "builtin_interfaces/msg/Duration": "duration"}
_INT_RANGES = {
    "int8": (-(2**7), 2**7 - 1),
    "uint8": (0, 2**8 - 1),
    "byte": (0, 2**8 - 1),
    "char": (0, 2**8 - 1),
    "int16": (-(2**15), 2**15 - 1),
    "uint16": (0, 2**16 - 1),
    "int32": (-(2**31), 2**31 - 1),
    "uint32": (0, 2**32 - 1),
    "int64": (-(2**63), 2**63 - 1),
    "uint64": (0, 2**64 - 1),
}
_FLOATS = {"float32", "float64"}
_BYTES = {"uint8", "char", "byte"}  # arrays of these travel as base64 in JSON, as bytes in CBOR
_GENPY_DIRS = ("/usr/lib/python3/dist-packages", *sorted(glob.glob("/opt/ros/*/lib/python3/dist-packages")))


def ros1_name(type_: str) -> str:
    """Return 'pkg/Type' for 'pkg/Type' or 'pkg/msg/Type'; raise BridgeError otherwise."""
    parts = type_.strip("/").split("/")
    if len(parts) == 3 and parts[1] in ("msg", "srv"):
        parts = [parts[0], parts[2]]
    if len(parts) != 2 or not all(p and p.replace("_", "").isalnum() for p in parts):
        raise BridgeError(f"{type_!r} is not a ROS type ('package/Type')")
    return "/".join(parts)


def _store_name(ros1: str, kind: str = "msg") -> str:
    package, name = ros1.split("/")
    return f"{package}/{kind}/{name}"


class Ros1Types:
    """A rosbags type store that grows with the definitions the graph shows it."""

    def __init__(self) -> None:
        from rosbags.typesys import Stores, get_typestore

        self.store = get_typestore(Stores.ROS1_NOETIC)
        self._numpy = __import__("numpy")

    # ------------------------------------------------------------------ definitions

    def learn(self, type_: str, definition: str) -> None:
        """Add a type from a connection header's ``message_definition`` (ignored when known or unreadable)."""
        name = _store_name(ros1_name(type_))
        if name in self.store.fielddefs or not definition:
            return
        self._register(definition, name)

    def _register(self, text: str, name: str) -> None:
        from rosbags.typesys import TypesysError, get_types_from_msg

        try:
            types = get_types_from_msg(text, name)
        except Exception as exc:  # the parser's errors carry no common base
            raise BridgeError(f"cannot read the definition of {name}: {exc}") from None
        # A definition may name types it does not define (a .msg file): find those too.
        for _, (_, fields) in list(types.items()):
            for _, desc in fields:
                for ref in self._references(desc):
                    if ref not in types and ref not in self.store.fielddefs:
                        self.ensure_message(ref)
        try:
            self.store.register(types)
        except TypesysError as exc:
            logger.info("rosbridge: keeping the known definition: %s", exc)

    @staticmethod
    def _references(desc: Any) -> list[str]:
        kind, args = desc
        if int(kind) == 2:  # NAME
            return [args]
        if int(kind) in (3, 4):  # ARRAY, SEQUENCE
            (sub_kind, sub_args), _ = args
            return [sub_args] if int(sub_kind) == 2 else []
        return []

    def ensure_message(self, type_: str) -> str:
        """Make a message type known; return its store name; raise BridgeError when nowhere to be found."""
        name = type_ if "/msg/" in type_ else _store_name(ros1_name(type_))
        if name in self.store.fielddefs:
            return name
        package, _, short = name.split("/")
        text = self._genpy_text(package, "msg", f"_{short}.py", short) or self._file_text(package, "msg", short)
        if text is None:
            raise BridgeError(f"unknown message type {package}/{short}: no definition found on this robot")
        self._register(text, name)
        return name

    def ensure_service(self, type_: str) -> tuple[str, str]:
        """Make a service type known; return the store names of its request and response."""
        package, short = ros1_name(type_).split("/")
        # rosbags names every parsed type pkg/msg/Name: the request and response are kept that way too.
        request, response = f"{package}/msg/{short}_Request", f"{package}/msg/{short}_Response"
        if request in self.store.fielddefs and response in self.store.fielddefs:
            return request, response
        texts: tuple[str | None, str | None] = (
            self._genpy_text(package, "srv", f"_{short}.py", short + "Request"),
            self._genpy_text(package, "srv", f"_{short}.py", short + "Response"),
        )
        if texts[0] is None or texts[1] is None:
            text = self._file_text(package, "srv", short)
            if text is None:
                raise BridgeError(f"unknown service type {package}/{short}: no definition found on this robot")
            head, sep, tail = text.partition("\n---")
            texts = (head, tail.partition("\n")[2] if sep else "")
        self._register(texts[0] or "", request)
        self._register(texts[1] or "", response)
        return request, response

    @staticmethod
    def _genpy_text(package: str, kind: str, module: str, cls: str) -> str | None:
        for root in _GENPY_DIRS:
            path = Path(root, package, kind, module)
            if not path.is_file():
                continue
            try:
                tree = ast.parse(path.read_text())
            except (OSError, SyntaxError, ValueError):
                return None
            for node in tree.body:
                if isinstance(node, ast.ClassDef) and node.name == cls:
                    for item in node.body:
                        if (
                            isinstance(item, ast.Assign)
                            and any(isinstance(t, ast.Name) and t.id == "_full_text" for t in item.targets)
                            and isinstance(item.value, ast.Constant)
                            and isinstance(item.value.value, str)
                        ):
                            return item.value.value
        return None

    @staticmethod
    def _file_text(package: str, kind: str, short: str) -> str | None:
        roots = [p for p in os.environ.get("ROS_PACKAGE_PATH", "").split(os.pathsep) if p]
        roots += [str(Path(sys.prefix) / "share"), *sorted(glob.glob("/opt/ros/*/share")), "/usr/share"]
        for root in roots:
            for path in (Path(root, package, kind, f"{short}.{kind}"), Path(root, kind, f"{short}.{kind}")):
                if path.is_file():
                    try:
                        return path.read_text()
                    except OSError:
                        continue
        return None

    def definition(self, type_: str) -> tuple[str, str]:
        """Return (message_definition, md5sum) of a message type, as a ROS 1 publisher announces them."""
        return self.store.generate_msgdef(self.ensure_message(type_), ros_version=1)

    # ------------------------------------------------------------------ bytes <-> plain data

    def decode(self, name: str, raw: bytes | memoryview) -> dict[str, Any]:
        """Return a serialized message as plain data (ROS 1 spelling of time: secs/nsecs)."""
        try:
            message = self.store.deserialize_ros1(raw, name)
        except Exception as exc:  # a truncated or foreign message
            raise BridgeError(f"cannot read a {name} message: {exc}") from None
        plain = self._plain(message)
        assert isinstance(plain, dict)
        return plain

    def _plain(self, value: Any) -> Any:
        name = getattr(value, "__msgtype__", None)
        if name is not None:
            if name in TIME_TYPES:
                return {"secs": value.sec, "nsecs": value.nanosec}
            return {key: self._plain(getattr(value, key)) for key, _ in self.store.fielddefs[name][1]}
        if isinstance(value, self._numpy.ndarray):
            if value.dtype == self._numpy.uint8:
                return value.tobytes()
            return value.tolist()
        if isinstance(value, list):
            return [self._plain(item) for item in value]
        return value

    def encode(self, name: str, data: dict[str, Any]) -> bytes:
        """Serialize plain data as a message; raise BridgeError naming the first bad field."""
        message = self._build(name, data, name.replace("/msg/", "/").replace("/srv/", "/"))
        return bytes(self.store.serialize_ros1(message, name))

    def _build(self, name: str, data: Any, path: str) -> Any:
        cls = self.store.types[name]
        if data is None:
            data = {}
        if not isinstance(data, dict):
            raise BridgeError(f"{path}: expected an object, not {type(data).__name__}")
        if name in TIME_TYPES:
            secs = data.get("secs", data.get("sec", 0))
            nsecs = data.get("nsecs", data.get("nanosec", 0))
            kind = "uint32" if name.endswith("Time") else "int32"
            return cls(sec=self._base(kind, secs, f"{path}.secs"), nanosec=self._base(kind, nsecs, f"{path}.nsecs"))
        fields = self.store.fielddefs[name][1]
        names = {field for field, _ in fields}
        for key in data:
            if key not in names:
                raise BridgeError(f"{path} has no field {key!r} (fields: {', '.join(sorted(names))})")
        kwargs = {field: self._value(desc, data.get(field), f"{path}.{field}") for field, desc in fields}
        return cls(**kwargs)

    def _value(self, desc: Any, value: Any, path: str) -> Any:
        kind, args = desc
        kind = int(kind)
        if kind == 1:  # BASE
            return self._base(args[0], value, path)
        if kind == 2:  # NAME
            return self._build(args, value, path)
        (sub_kind, sub_args), length = args
        fixed = length if kind == 3 else 0
        np = self._numpy
        if int(sub_kind) == 1:
            base = sub_args[0]
            if base == "string":
                items = [] if value is None else value
                if not isinstance(items, list):
                    raise BridgeError(f"{path}: expected a list of strings")
                result = [self._base("string", item, f"{path}[{i}]") for i, item in enumerate(items)]
                if fixed and len(result) != fixed:
                    raise BridgeError(f"{path}: expected {fixed} items, not {len(result)}")
                return result or ([""] * fixed)
            dtype = np.dtype("bool" if base == "bool" else "uint8" if base in _BYTES else base)
            if value is None:
                return np.zeros(fixed, dtype=dtype)
            if base in _BYTES and isinstance(value, str):
                try:
                    array = np.frombuffer(base64.b64decode(value, validate=True), dtype=np.uint8)
                except ValueError:
                    raise BridgeError(f"{path}: expected base64 text or a list of numbers") from None
            elif base in _BYTES and isinstance(value, bytes | bytearray):
                array = np.frombuffer(bytes(value), dtype=np.uint8)
            elif isinstance(value, list):
                array = np.array([self._base(base, item, f"{path}[{i}]") for i, item in enumerate(value)], dtype=dtype)
            else:
                raise BridgeError(f"{path}: expected a list, not {type(value).__name__}")
            if fixed and len(array) != fixed:
                raise BridgeError(f"{path}: expected {fixed} items, not {len(array)}")
            return array
        items = [] if value is None else value
        if not isinstance(items, list):
            raise BridgeError(f"{path}: expected a list of {sub_args}")
        result = [self._build(sub_args, item, f"{path}[{i}]") for i, item in enumerate(items)]
        if fixed and not result:
            result = [self._build(sub_args, {}, path) for _ in range(fixed)]
        if fixed and len(result) != fixed:
            raise BridgeError(f"{path}: expected {fixed} items, not {len(result)}")
        return result

    @staticmethod
    def _base(base: str, value: Any, path: str) -> Any:
        if base == "string":
            if value is None:
                return ""
            if not isinstance(value, str):
                raise BridgeError(f"{path}: expected a string, not {type(value).__name__}")
            return value
        if base == "bool":
            if value is None:
                return False
            if not isinstance(value, bool | int):
                raise BridgeError(f"{path}: expected a boolean, not {type(value).__name__}")
            return bool(value)
        if base in _FLOATS:
            if value is None:
                return 0.0
            if isinstance(value, bool) or not isinstance(value, int | float):
                raise BridgeError(f"{path}: expected a number, not {type(value).__name__}")
            return float(value)
        bounds = _INT_RANGES.get(base)
        if bounds is None:
            raise BridgeError(f"{path}: unsupported field type {base}")
        if value is None:
            return 0
        if isinstance(value, float) and value.is_integer():
            value = int(value)
        if isinstance(value, bool) or not isinstance(value, int):
            raise BridgeError(f"{path}: expected an integer, not {value!r}"[:200])
        if not bounds[0] <= value <= bounds[1]:
            raise BridgeError(f"{path}: {value} is out of range for {base}")
        return value

    # ------------------------------------------------------------------ rosapi

    def message_details(self, type_: str) -> list[dict[str, Any]]:
        """Return rosapi's TypeDefs of a type and the types inside it."""
        out: list[dict[str, Any]] = []
        seen: set[str] = set()
        queue = [self.ensure_message(type_)]
        while queue:
            name = queue.pop(0)
            if name in seen:
                continue
            seen.add(name)
            consts, fields = self.store.fielddefs[name]
            typedef: dict[str, Any] = {
                "type": name.replace("/msg/", "/").replace("/srv/", "/"),
                "fieldnames": [],
                "fieldtypes": [],
                "fieldarraylen": [],
                "examples": [],
                "constnames": [c[0] for c in consts],
                "constvalues": [str(c[2]) for c in consts],
            }
            for field, (node_kind, args) in fields:
                kind = int(node_kind)
                length = -1
                inner: Any = (kind, args)
                if kind in (3, 4):
                    inner, length = args[0], (int(args[1]) if kind == 3 else 0)
                inner_kind, inner_args = int(inner[0]), inner[1]
                if inner_kind == 2:
                    spelled = TIME_TYPES.get(inner_args) or inner_args.replace("/msg/", "/")
                    if inner_args not in TIME_TYPES:
                        queue.append(inner_args)
                else:
                    spelled = inner_args[0]
                typedef["fieldnames"].append(field)
                typedef["fieldtypes"].append(spelled)
                typedef["fieldarraylen"].append(length)
                typedef["examples"].append("[]" if length >= 0 else "{}" if inner_kind == 2 else _example(spelled))
            out.append(typedef)
        return out


def _example(base: str) -> str:
    if base == "string":
        return ""
    if base == "bool":
        return "False"
    return "0.0" if base in _FLOATS else "0"

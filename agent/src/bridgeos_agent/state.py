"""What the Robot Controller knows of its Skills, and the file that keeps it across agent restarts."""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import os
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from bridgeos_agent.logonce import LogOnce
from bridgeos_agent.protocol import ComponentStatusName as CS
from bridgeos_agent.protocol import ProtocolError
from bridgeos_agent.protocol import SkillStatusName as SS
from bridgeos_agent.robotconfig import RobotConfig, parse_robot_config
from bridgeos_agent.skillconfig import SkillConfig, parse_skill_config
from bridgeos_agent.supervisor import SkillSupervisor

logger = logging.getLogger("bridgeos_agent")

__all__ = ["SavedState", "SkillRecord", "StateFile", "find_component", "find_skill", "previous_placement"]


@dataclass
class SkillRecord:
    """What the controller knows of one Skill on this robot."""

    config: SkillConfig
    status: SS = SS.STOPPED
    locations: dict[str, str | None] = field(default_factory=dict)  # component -> robot|cloud|None
    statuses: dict[str, CS] = field(default_factory=dict)
    supervisor: SkillSupervisor | None = None
    # What the cloud reported of each cloud copy: {"runtime", "id", "address", "ports": {"<port>": <port>}}.
    cloud_containers: dict[str, dict[str, Any]] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        """Return what survives an agent restart."""
        return {
            "config": self.config.model_dump(mode="json"),
            "status": str(self.status),
            "locations": self.locations,
        }

    def context(self, name: str) -> Any:
        """Return what the Skill's supervisor holds under ``name`` (``router``, ``manager``, ``env``), if any."""
        return self.supervisor.context.get(name) if self.supervisor is not None else None


def find_skill(skills: Mapping[str, SkillRecord], skill_id: str) -> SkillRecord:
    """Return a Skill's record; ProtocolError naming ``data.skill`` if this robot has none."""
    record = skills.get(skill_id)
    if record is None:
        raise ProtocolError(f"no skill {skill_id!r} on this robot", field="data.skill", code="not_found")
    return record


def find_component(skills: Mapping[str, SkillRecord], skill_id: str, name: str) -> SkillRecord:
    """Return the record of the Skill that has this component; ProtocolError if there is none."""
    record = find_skill(skills, skill_id)
    if name not in record.config.components:
        raise ProtocolError(f"skill {skill_id!r} has no component {name!r}", field="data.component", code="not_found")
    return record


@dataclass
class SavedState:
    """What the last agent left on disk."""

    config: RobotConfig | None = None
    skills: dict[str, SkillRecord] = field(default_factory=dict)
    runtime: dict[str, Any] = field(default_factory=dict)


class StateFile:
    """Keep the robot config, the Skills and the runtime's state in one JSON file, written atomically."""

    def __init__(self, path: Path, collect: Callable[[], dict[str, Any]]) -> None:
        self.path = path
        self._collect = collect
        self._pending = False
        self._saving = LogOnce(logger, f"saving the agent's state to {path}")

    def load(self, say: Callable[[str], None]) -> SavedState | None:
        """Read what the last agent saved (None if there is no file or it is unreadable)."""
        try:
            state = json.loads(self.path.read_text())
        except FileNotFoundError:
            return None
        except (OSError, ValueError) as exc:
            say(f"ignoring unreadable state file {self.path}: {exc}")
            return None
        saved = SavedState(runtime=state.get("runtime", {}))
        if state.get("config"):
            with contextlib.suppress(ValueError):
                saved.config = parse_robot_config(state["config"])
        for skill_id, entry in state.get("skills", {}).items():
            try:
                config = parse_skill_config(entry["config"])
            except (ValueError, KeyError):
                continue
            record = SkillRecord(config=config, status=SS(entry.get("status", "stopped")))
            record.locations = {c: entry.get("locations", {}).get(c) for c in config.components}
            saved.skills[skill_id] = record
        return saved

    def save_soon(self) -> None:
        """Save within 0.2 s, once for every change made meanwhile."""
        if not self._pending:
            self._pending = True
            asyncio.get_running_loop().call_later(0.2, self.save_now)

    def save_now(self) -> None:
        """Write the state now; on a full disk keep the last saved state and say so."""
        self._pending = False
        tmp = self.path.with_suffix(".tmp")
        try:
            tmp.write_text(json.dumps(self._collect()))
            os.replace(tmp, self.path)
        except OSError as exc:
            # The agent runs on (its state is in memory); only a restart now would start from the last save.
            with contextlib.suppress(OSError):
                tmp.unlink()
            self._saving.failed(exc)
        else:
            self._saving.worked()


def previous_placement(data_dir: Path, skill_id: str) -> dict[str, str]:
    """Return where each movable component of a Skill ran when its manager last stopped."""
    try:
        saved = json.loads((data_dir / "models" / skill_id / "placement.json").read_text())
    except (OSError, ValueError):
        return {}
    if not isinstance(saved, dict):
        return {}
    return {name: where for name, where in saved.items() if where in ("robot", "cloud")}

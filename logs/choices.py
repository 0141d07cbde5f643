"""Choices of log fields: where a line was printed, on which stream, at which level."""

from __future__ import annotations

from bridgeos_agent.protocol import LOG_LEVELS

# Levels are stored as their rank, so "at least warning" is one comparison (a line without one counts as info).
LEVEL_RANK: dict[str, int] = {name: rank for rank, name in enumerate(LOG_LEVELS)}
LEVEL_NAME: dict[int, str] = {rank: name for name, rank in LEVEL_RANK.items()}
UNLEVELLED_RANK = LEVEL_RANK["info"]

LOCATIONS = ("robot", "cloud")
STREAMS = ("stdout", "stderr")

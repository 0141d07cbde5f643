"""The fault suite's scenarios: each breaks one real part on purpose and reports what survived.

A scenario is a module here with `NAME`, `INJECTS` (one line: what it breaks) and
`run(quick: bool) -> list[Outcome]` (one outcome per case it tries). `SCENARIOS` lists them in
the order the runner plays them; `summary()` folds every outcome into the runner's last line.
"""

from __future__ import annotations

import importlib
from dataclasses import asdict, dataclass, field
from types import ModuleType

# Module names under benchmarks/chaos/, in the order the runner plays them.
SCENARIOS = ("processes", "stores", "link", "agentkill", "diskfull", "hog", "hostile", "load")


@dataclass
class Outcome:
    """What one injected fault did: sent, stored, lost, duplicated, time to recover, and whether it passed."""

    scenario: str
    injected: str
    sent: int = 0
    stored: int = 0
    lost: int = 0
    duplicated: int = 0
    recover_s: float | None = None
    passed: bool = False
    detail: str = ""
    # Figures a scenario reports beyond the table's columns (takeover_s, fuzz_frames, p99 ...).
    figures: dict[str, float | int | None] = field(default_factory=dict)

    def row(self) -> dict:
        return asdict(self)


def load(name: str) -> ModuleType:
    """Import one scenario module by its name in SCENARIOS."""
    if name not in SCENARIOS:
        raise ValueError(f"unknown scenario {name!r}; known: {', '.join(SCENARIOS)}")
    return importlib.import_module(f"benchmarks.chaos.{name}")


def _largest(outcomes: list[Outcome], key: str) -> float | None:
    values = [o.figures[key] for o in outcomes if o.figures.get(key) is not None]
    return max(values) if values else None  # type: ignore[type-var]


def _total(outcomes: list[Outcome], key: str) -> int:
    return int(sum(o.figures.get(key) or 0 for o in outcomes))


def summary(outcomes: list[Outcome]) -> dict:
    """Fold the outcomes into the runner's last line (keys pinned by issue 20)."""
    return {
        "lost": sum(o.lost for o in outcomes),
        "duplicated": sum(o.duplicated for o in outcomes),
        "takeover_s": _largest(outcomes, "takeover_s"),
        "reconnect_s": _largest(outcomes, "reconnect_s"),
        "fuzz_frames": _total(outcomes, "fuzz_frames"),
        "fuzz_server_errors": _total(outcomes, "fuzz_server_errors"),
        "cross_tenant_attempts": _total(outcomes, "cross_tenant_attempts"),
        "cross_tenant_allowed": _total(outcomes, "cross_tenant_allowed"),
        "cross_role_attempts": _total(outcomes, "cross_role_attempts"),
        "cross_role_allowed": _total(outcomes, "cross_role_allowed"),
        "scenarios": len(outcomes),
        "scenarios_passed": sum(o.passed for o in outcomes),
    }

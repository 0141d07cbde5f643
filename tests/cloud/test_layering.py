"""The cloud's apps depend one way, read from their import statements (README, "Layers").

Every app has a core (models, services, the cloud orchestration, ...) and doors (REST views
and serializers, consumers, routes, admin, Celery tasks, management commands). Cores depend
only on the cores of the apps below them and on the shared base (`bridgeos_cloud` minus its
wiring); doors may use any app. Nothing imports inside a function to dodge a cycle: where a
lower app must reach a higher one it sends a Django signal the higher app receives.
"""

from __future__ import annotations

import ast
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
# Lowest first: everything records events and metrics (monitoring); robots own identities and
# links; networks serve robots; skills run on robots; the dashboard shows all of it.
LAYERS = ["monitoring", "robots", "network", "skills", "recordings", "logs", "dashboard"]
BASE = "bridgeos_cloud"
# The project's wiring: settings, URL and WebSocket routes, the ASGI entry point.
WIRING = {"settings", "urls", "routing", "asgi"}
DOOR_PARTS = {"api", "management"}
# An app config is its app's wiring: ready() connects receivers and registers tasks.
DOOR_MODULES = {"admin", "apps", "consumers", "routing", "urls", "views", "tasks"}
PROJECT = {*LAYERS, BASE}


@dataclass(frozen=True)
class Import:
    source: Path
    line: int
    target: str
    local: bool


def module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imports_of(path: Path) -> list[Import]:
    """Return the project modules a file imports, saying which imports sit inside a function."""
    tree = ast.parse(path.read_text(), filename=str(path))
    package = module_name(path).split(".")
    if path.name != "__init__.py":
        package = package[:-1]
    found: list[Import] = []

    def visit(node: ast.AST, local: bool) -> None:
        for child in ast.iter_child_nodes(node):
            inner = local or isinstance(child, ast.FunctionDef | ast.AsyncFunctionDef)
            targets: list[str] = []
            if isinstance(child, ast.Import):
                targets = [alias.name for alias in child.names]
            elif isinstance(child, ast.ImportFrom):
                base = package[: len(package) - child.level + 1] if child.level else []
                module = ".".join([*base, *(child.module or "").split(".")]).strip(".")
                targets = [module] if child.module else [f"{module}.{alias.name}" for alias in child.names]
            for target in targets:
                if target.split(".")[0] in PROJECT:
                    found.append(Import(path, child.lineno, target, local))
            visit(child, inner)

    visit(tree, False)
    return found


def is_door(module: str) -> bool:
    parts = module.split(".")
    return parts[0] in LAYERS and (bool(DOOR_PARTS & set(parts[1:])) or parts[-1] in DOOR_MODULES)


def is_wiring(module: str) -> bool:
    parts = module.split(".")
    return parts[0] == BASE and len(parts) > 1 and parts[1] in WIRING


def source_files() -> list[Path]:
    files = []
    for top in PROJECT:
        files += [p for p in (ROOT / top).rglob("*.py") if "migrations" not in p.parts]
    return sorted(files)


def violations() -> list[str]:
    problems = []
    for path in source_files():
        module = module_name(path)
        app = module.split(".")[0]
        for found in imports_of(path):
            where = f"{found.source.relative_to(ROOT)}:{found.line} imports {found.target}"
            target_app = found.target.split(".")[0]
            if found.local and not (path.name == "apps.py" and target_app == app):
                problems.append(f"{where} inside a function")
            if app == BASE:
                if not is_wiring(module) and target_app != BASE:
                    problems.append(f"{where}: the base imports no app")
                continue
            if is_door(module):
                continue
            if is_door(found.target) or is_wiring(found.target):
                problems.append(f"{where}: a core imports no door")
            elif target_app in LAYERS and LAYERS.index(target_app) > LAYERS.index(app):
                problems.append(f"{where}: {app} sits below {target_app}")
    return problems


def test_the_apps_depend_one_way_without_local_imports():
    assert violations() == []


def test_the_check_sees_an_upward_import_and_a_local_one(tmp_path):
    # The check itself reads imports as they are written: an upward and a function-local import.
    module = ROOT / "robots" / "_layering_probe.py"
    module.write_text("from skills.models import Skill\n\n\ndef late():\n    from dashboard import services\n")
    try:
        found = [problem for problem in violations() if "_layering_probe" in problem]
    finally:
        module.unlink()
    assert any("robots sits below skills" in problem for problem in found)
    assert any("inside a function" in problem for problem in found)

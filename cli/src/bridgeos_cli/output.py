"""Tables for people, JSON for scripts, and the state every command shares."""

from __future__ import annotations

import json
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, TypeVar

import click

if TYPE_CHECKING:
    from .client import Api

F = TypeVar("F", bound=Callable[..., Any])


@dataclass
class State:
    """What the root command and its options settle for the command that runs."""

    json: bool = False
    _api: Api | None = field(default=None, repr=False)

    def api(self) -> Api:
        """Return the Robot API client of the current login (NotLoggedIn without one)."""
        if self._api is None:
            from . import config
            from .client import Api

            self._api = Api(config.current())
        return self._api

    def close(self) -> None:
        if self._api is not None:
            self._api.close()


def state() -> State:
    """Return the running command's shared state."""
    context = click.get_current_context()
    root = context.find_root()
    if root.obj is None:
        root.obj = State()
        root.call_on_close(root.obj.close)
    return root.obj


def _set_json(context: click.Context, parameter: click.Parameter, value: bool) -> bool:
    if value:
        state().json = True
    return value


def json_option(function: F) -> F:
    """Add --json to a command: print the API's answer as JSON on stdout instead of a table."""
    return click.option(
        "--json",
        "as_json",
        is_flag=True,
        expose_value=False,
        is_eager=True,
        callback=_set_json,
        help="Print JSON for scripts instead of a table.",
    )(function)


def emit_json(data: Any) -> None:
    """Print data as JSON on stdout."""
    click.echo(json.dumps(data, indent=2, default=str))


def cell(value: Any) -> str:
    """Render one table cell: empty for None, compact JSON for structures."""
    if value is None:
        return ""
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, dict | list):
        if isinstance(value, dict):
            return ",".join(f"{k}={v}" for k, v in value.items())
        return ",".join(str(item) for item in value)
    return str(value)


def table(rows: Iterable[dict], columns: Sequence[str | Sequence[str]], *, empty: str = "(none)") -> None:
    """Print rows as an aligned table with the given columns (a key, or (heading, key))."""
    pairs = [(c, c) if isinstance(c, str) else (c[0], c[1]) for c in columns]
    body = [[cell(row.get(key)) for _, key in pairs] for row in rows]
    if not body:
        click.echo(empty, err=True)
        return
    headings = [heading.upper() for heading, _ in pairs]
    widths = [max(len(text) for text in column) for column in zip(headings, *body, strict=True)]
    for line in [headings, *body]:
        click.echo("  ".join(text.ljust(width) for text, width in zip(line, widths, strict=True)).rstrip())


def fields(data: dict, keys: Sequence[str] | None = None) -> None:
    """Print one object as `key: value` lines."""
    keys = keys or list(data)
    width = max((len(key) for key in keys), default=0)
    for key in keys:
        click.echo(f"{key + ':':<{width + 1}} {cell(data.get(key))}")


def show(data: Any, render: Callable[[Any], None]) -> None:
    """Print data as JSON when --json was given, else with the command's own renderer."""
    if state().json:
        emit_json(data)
    else:
        render(data)

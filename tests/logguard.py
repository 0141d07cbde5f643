"""The log guard: a test fails when what it ran logged an ERROR line or a traceback it did not expect.

Fixtures that start daphne, a Celery worker or an agent process hand their log files to ``watch``;
records logged in the test process itself (agents, routers and bridges run in it too) are caught by
a handler on the root logger. After each test's teardown the lines written since the last test are
read and every ERROR or CRITICAL line and every traceback is one *entry* (with the lines that carry
on from it). An entry fails the test unless a pattern of its ``log_errors`` mark matches it:

    @pytest.mark.log_errors(r"robot rob-1: bad frame", r"ConnectionResetError")

so a test that provokes an error on purpose says which one. Lines a long-lived server writes
between two tests belong to the later one: it is the test that saw them.
"""

from __future__ import annotations

import logging
import re
from dataclasses import dataclass, field
from pathlib import Path

import pytest

__all__ = ["BAD_LINE", "bad_entries", "is_bad", "watch"]

# A log line at ERROR or above, in the formats of this project's parts (cloud and agent:
# "time LEVEL name: message"; Celery: "[time: ERROR/MainProcess] ..."; Go's logrus, as the
# registry writes: 'time="..." level=error msg=...'), or a traceback.
BAD_LINE = re.compile(r"\b(ERROR|CRITICAL)\b|(?:^|\s)level=(error|fatal|panic)\b|Traceback \(most recent call last\)")
# daphne's access log: a request line, whose URL is the client's text (a query may well say level=error).
ACCESS_LINE = re.compile(r'^\S+:\d+ - - \[[^\]]+\] "')
# Where a new log record begins: a timestamp, a bracketed timestamp, logrus's time="...", or Python's default format.
RECORD_START = re.compile(
    r'^(\[?\d{4}-\d\d-\d\d[ T]\d\d:\d\d|time="\d{4}-|[A-Z]+:[\w.]+:|(DEBUG|INFO|WARNING|ERROR|CRITICAL)\b)'
)
MAX_ENTRY_LINES = 60


def is_bad(line: str) -> bool:
    """Tell whether a log line is an error or a traceback's start (a request line of an access log never is)."""
    return BAD_LINE.search(line) is not None and not ACCESS_LINE.match(line)


def bad_entries(text: str) -> list[str]:
    """Split a log's text into its bad entries: an ERROR line or a traceback with the lines that carry on from it."""
    entries: list[str] = []
    lines = text.splitlines()
    index = 0
    while index < len(lines):
        line = lines[index]
        if not is_bad(line):
            index += 1
            continue
        entry = [line]
        index += 1
        # A traceback carries on until its exception line; any entry until the next record begins.
        while index < len(lines) and len(entry) < MAX_ENTRY_LINES:
            following = lines[index]
            if (RECORD_START.match(following) or ACCESS_LINE.match(following)) and not following.startswith(
                "Traceback"
            ):
                break
            entry.append(following)
            index += 1
        entries.append("\n".join(entry))
    return entries


@dataclass
class _Watched:
    """A log file and how far the guard has read it."""

    path: Path
    offset: int = 0


@dataclass
class _Guard:
    """The files watched, the records caught in this process, and the test now running."""

    files: dict[Path, _Watched] = field(default_factory=dict)
    records: list[str] = field(default_factory=list)

    def read_new(self) -> list[tuple[str, str]]:
        """Return (where, entry) for every bad entry written since the last read."""
        found: list[tuple[str, str]] = []
        for path, watched in list(self.files.items()):
            try:
                with path.open("rb") as log:
                    log.seek(watched.offset)
                    data = log.read()
            except FileNotFoundError:
                del self.files[path]  # its test's directory is gone, and its process with it
                continue
            # Only whole lines: a line half written now is read whole after the next test.
            end = data.rfind(b"\n") + 1
            watched.offset += end
            found += [(path.name, entry) for entry in bad_entries(data[:end].decode(errors="replace"))]
        found += [("this process", record) for record in self.records]
        self.records.clear()
        return found


_guard = _Guard()


def watch(path: Path | str) -> Path:
    """Have the guard read a log file after every test from now on (only what is written from now on)."""
    path = Path(path)
    offset = path.stat().st_size if path.exists() else 0
    _guard.files.setdefault(path, _Watched(path, offset))
    return path


class _Catch(logging.Handler):
    """Keep every record at ERROR or above logged in this process, formatted with its traceback."""

    def __init__(self) -> None:
        super().__init__(logging.ERROR)
        self.setFormatter(logging.Formatter("%(levelname)s %(name)s: %(message)s"))

    def emit(self, record: logging.LogRecord) -> None:
        try:
            _guard.records.append(self.format(record))
        except Exception:  # a record that cannot be formatted is still an error
            _guard.records.append(f"{record.levelname} {record.name}: {record.msg!r}")


def pytest_configure(config: pytest.Config) -> None:
    config.addinivalue_line(
        "markers",
        "log_errors(*patterns): the ERROR lines or tracebacks (regular expressions) this test provokes on purpose",
    )


_catch = _Catch()


@pytest.hookimpl(tryfirst=True)
def pytest_runtest_setup(item: pytest.Item) -> None:
    # Django's logging settings (and an agent's CLI) replace the root logger's handlers: attach again.
    root = logging.getLogger()
    if _catch not in root.handlers:
        root.addHandler(_catch)


@pytest.hookimpl(wrapper=True)
def pytest_runtest_teardown(item: pytest.Item, nextitem: pytest.Item | None):
    result = yield
    patterns = [re.compile(p) for mark in item.iter_markers("log_errors") for p in mark.args]
    unexpected = [
        f"{where}: {entry}" for where, entry in _guard.read_new() if not any(p.search(entry) for p in patterns)
    ]
    if unexpected:
        shown = "\n\n".join(entry[:3000] for entry in unexpected[:10])
        more = f"\n\n... and {len(unexpected) - 10} more" if len(unexpected) > 10 else ""
        pytest.fail(
            f"the log guard found {len(unexpected)} unexpected error(s) in the logs of what this test ran "
            f"(mark the test @pytest.mark.log_errors(pattern) if it provokes them on purpose):\n\n{shown}{more}",
            pytrace=False,
        )
    return result

"""The make-run path: store_lines, queries and retention on the embedded SQLite database (no PostgreSQL)."""

from __future__ import annotations

import json
import os
import subprocess
import sys

from tests.conftest import ROOT

SCRIPT = r"""
import json, time
from django.contrib.auth import get_user_model
from logs.services import LogFilters, page_of_lines, prune_logs, store_lines, dropped_count
from robots.services import create_robot

create_robot("sq-bot", get_user_model().objects.create_user("sq-owner"))
now = time.time()
lines = [
    {"seq": n, "ts": now - 100 + n, "stream": "stdout", "level": "warning" if n % 2 else None, "text": f"Line {n} at 100%"}
    for n in range(1, 11)
]
result = {
    "first": store_lines("sq-bot", "sk", "cam", "robot", lines, dropped=2),
    "again": store_lines("sq-bot", "sk", "cam", "robot", lines),
    "ancient": store_lines("sq-bot", "sk", "cam", "robot", [{"seq": 11, "ts": now - 30 * 86400, "stream": "stderr", "text": "old"}]),
}
rows, _ = page_of_lines("sq-bot", LogFilters(q="LINE 3 "))
result["substring"] = [row.text for row in rows]
rows, _ = page_of_lines("sq-bot", LogFilters(q="100_"))
result["literal_wildcard"] = len(rows)
rows, _ = page_of_lines("sq-bot", LogFilters(q=r"line (2|4) ", regex=True), order="asc")
result["regex"] = [row.seq for row in rows]
rows, _ = page_of_lines("sq-bot", LogFilters(level="warning"), order="asc")
result["warning"] = [row.seq for row in rows]
seen, cursor = [], None
while True:
    rows, token = page_of_lines("sq-bot", LogFilters(), limit=4, cursor=cursor)
    seen += [row.seq for row in rows]
    if token is None:
        break
    from logs.services import decode_cursor
    cursor = decode_cursor(token)
result["pages"] = seen
result["dropped"] = dropped_count("sq-bot", LogFilters())
result["pruned"] = prune_logs()
print(json.dumps(result))
"""


def test_store_lines_and_queries_work_on_the_embedded_sqlite_database(tmp_path):
    env = {key: value for key, value in os.environ.items() if key != "DATABASE_URL"}
    env.update(BRIDGEOS_DATA_DIR=str(tmp_path), PYTHONPATH=os.pathsep.join([str(ROOT), str(ROOT / "agent" / "src")]))
    subprocess.run([sys.executable, "manage.py", "migrate", "-v0"], cwd=ROOT, env=env, check=True, timeout=300)
    assert (tmp_path / "db.sqlite3").exists()
    done = subprocess.run(
        [sys.executable, "manage.py", "shell", "-c", SCRIPT],
        cwd=ROOT,
        env=env,
        check=True,
        timeout=120,
        capture_output=True,
        text=True,
    )
    result = json.loads(done.stdout.strip().splitlines()[-1])
    assert result == {
        "first": 10,
        "again": 0,
        "ancient": 1,
        "substring": ["Line 3 at 100%"],
        "literal_wildcard": 0,
        "regex": [2, 4],
        "warning": [1, 3, 5, 7, 9],
        "pages": [10, 9, 8, 7, 6, 5, 4, 3, 2, 1, 11],
        "dropped": 2,
        "pruned": 1,
    }

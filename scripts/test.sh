#!/usr/bin/env bash
# Run the whole suite against the real PostgreSQL and Redis (never SQLite).
set -euo pipefail
cd "$(dirname "$0")/.."

export DATABASE_URL="${TEST_DATABASE_URL:-postgres://postgres@127.0.0.1:5432/test}"
# A Redis database of its own, so tests never see another process's queues or groups.
export REDIS_URL="${TEST_REDIS_URL:-redis://127.0.0.1:6379/14}"
# The tests' data directory: a fresh temporary one per run unless given, so no run sees another's files.
export BRIDGEOS_DATA_DIR="${BRIDGEOS_DATA_DIR:-$(mktemp -d /tmp/bridgeos-test.XXXXXX)}"
export ROS_MASTER_URI="${ROS_MASTER_URI:-http://127.0.0.1:11311}"
export PYTHONDONTWRITEBYTECODE=1
# Many tests present wrong credentials on purpose; the tests of the limit itself set their own.
export BRIDGEOS_AUTH_FAILURES="${BRIDGEOS_AUTH_FAILURES:-100000}"

echo "== tests: database ${DATABASE_URL%%\?*}, redis $REDIS_URL"
# The slowest tests in every log (CI's included), so a slowdown shows where it came from; a
# later --durations in the arguments wins.
exec .venv/bin/python -m pytest --durations=25 "$@"

#!/usr/bin/env bash
# `make run`: migrate, make an operator account, start daphne (and a Celery worker if Redis answers).
set -euo pipefail
cd "$(dirname "$0")/.."
PY=.venv/bin/python
HOST="${BRIDGEOS_HOST:-127.0.0.1}"
PORT="${BRIDGEOS_PORT:-8000}"

# Redis is the embedded default's optional extra: use it when it answers, else stay in-process.
if [ -z "${REDIS_URL:-}" ] && $PY - <<'PY' 2>/dev/null
import socket; socket.create_connection(("127.0.0.1", 6379), timeout=0.5).close()
PY
then
  export REDIS_URL="redis://127.0.0.1:6379/0"
fi

# Cloud copies of components: Swarm services when this machine runs a Swarm and has the local
# images, else processes (set BRIDGEOS_CLOUD_RUNTIME=swarm|docker|process to choose).
if [ -z "${BRIDGEOS_CLOUD_RUNTIME:-}" ]; then
  if [ "$(docker info --format '{{.Swarm.LocalNodeState}}' 2>/dev/null)" = active ] \
     && docker image inspect bridgeos/ros:noetic >/dev/null 2>&1; then
    export BRIDGEOS_CLOUD_RUNTIME=swarm
  else
    export BRIDGEOS_CLOUD_RUNTIME=process
  fi
fi
echo "== cloud runtime: $BRIDGEOS_CLOUD_RUNTIME"
echo "== database: ${DATABASE_URL:-SQLite file in ${BRIDGEOS_DATA_DIR:-.data}}"
$PY manage.py migrate --no-input -v 0
login=$($PY manage.py ensure_operator)

pids=()
fleet=""
stop() {
  trap - INT TERM EXIT
  echo; echo "== stopping"
  # The demo robots first (they stop their components), then what the cloud runs for them.
  if [ -n "$fleet" ]; then kill "$fleet" 2>/dev/null || true; wait "$fleet" 2>/dev/null || true; fi
  $PY manage.py cloud_down || true
  for pid in "${pids[@]}"; do kill "$pid" 2>/dev/null || true; done
  wait 2>/dev/null || true
}
trap stop INT TERM EXIT

if [ -n "${REDIS_URL:-}" ]; then
  echo "== celery worker on $REDIS_URL"
  .venv/bin/celery -A bridgeos_cloud worker --beat -l warning -c 2 &
  pids+=($!)
else
  echo "== no Redis: in-memory channel layer, tasks run in-process"
fi

scripts/daphne -b "$HOST" -p "$PORT" &
pids+=($!)

for _ in $(seq 1 100); do
  if $PY -c "import urllib.request; urllib.request.urlopen('http://$HOST:$PORT/api/health', timeout=1)" 2>/dev/null; then break; fi
  sleep 0.1
done
.venv/bin/python scripts/demo_fleet.py &
fleet=$!
pids+=($fleet)

cat <<MSG

  bridgeOS Cloud is running.
    Dashboard: http://$HOST:$PORT/
    Admin:     http://$HOST:$PORT/admin/
    API docs:  http://$HOST:$PORT/api/docs/
    Demo fleet: ${BRIDGEOS_DEMO_ROBOTS:-3} simulated robots (BRIDGEOS_DEMO_ROBOTS=0 for none)
    $login
  Press Ctrl-C to stop.

MSG
wait -n "${pids[@]}"

#!/usr/bin/env bash
# `make run`: migrate, make an operator account, start daphne (and a Celery worker if Redis answers).
# The terminal gets one status line per part and the login; every part's own output (access
# logs, the worker's banner, the demo fleet's moves) goes to a file under .data/logs named here.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=.venv/bin/python
HOST="${BRIDGEOS_HOST:-127.0.0.1}"
PORT="${BRIDGEOS_PORT:-8000}"
DATA_DIR="${BRIDGEOS_DATA_DIR:-.data}"
LOGS="$DATA_DIR/logs"
mkdir -p "$LOGS"
status() { printf '  %-12s %s\n' "$1:" "$2"; }

# Prometheus values of the processes of an earlier run would linger in the sums: start empty
# (monitoring/prometheus.py). Every process of this run shares the directory.
export PROMETHEUS_MULTIPROC_DIR="${PROMETHEUS_MULTIPROC_DIR:-$DATA_DIR/prometheus}"
rm -rf "$PROMETHEUS_MULTIPROC_DIR"
mkdir -p "$PROMETHEUS_MULTIPROC_DIR"

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
# The cloud's image registry (Debian's docker-registry), taking its tokens from this cloud, when
# it is installed; daphne is told its address so that Skills' images there are pinned by digest.
REGISTRY_PORT="${BRIDGEOS_REGISTRY_PORT:-5000}"
REALM_HOST="$HOST"; [ "$REALM_HOST" = 0.0.0.0 ] && REALM_HOST=127.0.0.1
registry_note=""
registry_shared=""  # the standing registry scripts/services.sh started for this data directory and cloud
registry_pid=$(cat "$DATA_DIR/registry/registry.pid" 2>/dev/null || true)
if [ -n "$registry_pid" ] && [ "$(cat "/proc/$registry_pid/comm" 2>/dev/null)" = docker-registry ] \
   && grep -qF "realm: \"http://$REALM_HOST:$PORT/api/registry/token\"" "$DATA_DIR/registry/config.yml" 2>/dev/null; then
  registry_shared=1
elif ! command -v docker-registry >/dev/null 2>&1; then
  registry_note="not installed: Skills' images are not pinned and robots pull nothing (scripts/services.sh registry)"
elif (exec 3<>"/dev/tcp/127.0.0.1/$REGISTRY_PORT") 2>/dev/null; then
  registry_note="port $REGISTRY_PORT is taken: not started (set BRIDGEOS_REGISTRY_PORT)"
fi
echo "bridgeOS Cloud: starting (logs in $LOGS/)"
status database "${DATABASE_URL:-SQLite file in $DATA_DIR}"
$PY manage.py migrate --no-input -v 0 >>"$LOGS/manage.log" 2>&1 || { echo "migrate failed, see $LOGS/manage.log" >&2; tail -5 "$LOGS/manage.log" >&2; exit 1; }
login=$($PY manage.py ensure_operator 2>>"$LOGS/manage.log")
status runtime "cloud copies run as $BRIDGEOS_CLOUD_RUNTIME"
if [ -n "$registry_shared" ]; then
  export BRIDGEOS_REGISTRY_HOST="${BRIDGEOS_REGISTRY_HOST:-127.0.0.1:$REGISTRY_PORT}"
elif [ -z "$registry_note" ]; then
  $PY manage.py registry_config --realm "http://$REALM_HOST:$PORT/api/registry/token" \
    --listen "127.0.0.1:$REGISTRY_PORT" --storage "$DATA_DIR/registry/storage" --out "$DATA_DIR/registry" \
    >>"$LOGS/manage.log" 2>&1 || { echo "registry_config failed, see $LOGS/manage.log" >&2; exit 1; }
  export BRIDGEOS_REGISTRY_HOST="${BRIDGEOS_REGISTRY_HOST:-127.0.0.1:$REGISTRY_PORT}"
fi

pids=()
fleet=""
stop() {
  trap - INT TERM EXIT
  echo; echo "bridgeOS Cloud: stopping"
  # The demo robots first (they stop their components), then what the cloud runs for them.
  if [ -n "$fleet" ]; then kill "$fleet" 2>/dev/null || true; wait "$fleet" 2>/dev/null || true; fi
  $PY manage.py cloud_down >>"$LOGS/manage.log" 2>&1 || true
  for pid in "${pids[@]}"; do kill "$pid" 2>/dev/null || true; done
  wait 2>/dev/null || true
}
# Ctrl-C (or a TERM) is how a user stops it: a clean stop, not a failure make would report.
trap 'stop; exit 0' INT TERM
trap stop EXIT

if [ -n "${REDIS_URL:-}" ]; then
  .venv/bin/celery -A bridgeos_cloud worker --beat -l warning -c 2 \
    --schedule "$DATA_DIR/celerybeat-schedule" >>"$LOGS/celery.log" 2>&1 &
  pids+=($!)
  status celery "worker and beat on $REDIS_URL (log $LOGS/celery.log)"
else
  status celery "no Redis: in-memory channel layer, tasks run in-process"
fi

scripts/daphne -b "$HOST" -p "$PORT" >>"$LOGS/daphne.log" 2>&1 &
daphne=$!
pids+=($daphne)

for _ in $(seq 1 300); do
  if $PY -c "import urllib.request; urllib.request.urlopen('http://$HOST:$PORT/api/health', timeout=1)" 2>/dev/null \
     || ! kill -0 "$daphne" 2>/dev/null; then break; fi
  sleep 0.1
done
status daphne "http://$HOST:$PORT/ (access log $LOGS/daphne.log)"
if [ -n "$registry_shared" ]; then
  status registry "127.0.0.1:$REGISTRY_PORT, started by scripts/services.sh, tokens from this cloud (docker login 127.0.0.1:$REGISTRY_PORT)"
elif [ -z "$registry_note" ]; then
  docker-registry serve "$DATA_DIR/registry/config.yml" >>"$LOGS/registry.log" 2>&1 &
  registry=$!
  pids+=($registry)
  # "running" below is a promise that `docker login` works at once: keep it on a slow machine.
  for _ in $(seq 1 150); do
    if (exec 3<>"/dev/tcp/127.0.0.1/$REGISTRY_PORT") 2>/dev/null || ! kill -0 "$registry" 2>/dev/null; then break; fi
    sleep 0.1
  done
  status registry "127.0.0.1:$REGISTRY_PORT, tokens from this cloud (docker login 127.0.0.1:$REGISTRY_PORT; log $LOGS/registry.log)"
else
  status registry "$registry_note"
fi
.venv/bin/python scripts/demo_fleet.py >>"$LOGS/demo_fleet.log" 2>&1 &
fleet=$!
pids+=($fleet)
if [ "${BRIDGEOS_DEMO_ROBOTS:-3}" -gt 0 ]; then
  status demo "${BRIDGEOS_DEMO_ROBOTS:-3} simulated robot(s) (log $LOGS/demo_fleet.log, agents in $DATA_DIR/agents/)"
else
  status demo "off (BRIDGEOS_DEMO_ROBOTS=0)"
fi
prometheus_port="${BRIDGEOS_PROMETHEUS_PORT:-9190}"
if (exec 3<>"/dev/tcp/127.0.0.1/$prometheus_port") 2>/dev/null; then
  status metrics "http://$HOST:$PORT/metrics, Prometheus at http://127.0.0.1:$prometheus_port/ (scripts/services.sh prometheus)"
else
  status metrics "http://$HOST:$PORT/metrics (no Prometheus on :$prometheus_port: scripts/services.sh prometheus)"
fi

cat <<MSG

  bridgeOS Cloud is running.
    Dashboard: http://$HOST:$PORT/
    Admin:     http://$HOST:$PORT/admin/
    API docs:  http://$HOST:$PORT/api/docs/
    $login
  Press Ctrl-C to stop.

MSG
status=0
wait -n "${pids[@]}" || status=$?
# Ctrl-C reaches every part at once, and one may end before this shell takes the signal: give
# the INT trap its turn (a clean stop, exit 0) before taking this for a part that died.
sleep 0.5
echo "bridgeOS Cloud: a part stopped by itself (status $status); see $LOGS/" >&2
exit 1

#!/bin/sh
# bridgeos-cloud SUBCOMMAND: run one part of bridgeOS Cloud in this container.
#   daphne    migrate (under a lock), then serve HTTP and WebSockets on 0.0.0.0:8000
#   worker    migrate (under a lock), then a Celery worker (BRIDGEOS_WORKER_CONCURRENCY, default 2)
#   beat      Celery beat (run exactly one)
#   migrate   apply migrations and make sure the operator account exists, then exit
#   manage    python manage.py ARGS...
#   health    exit 0 when this container's daphne answers /api/health
set -eu
cd /opt/bridgeos-cloud
# Django reads its secrets from *_FILE itself; the stock ensure_operator reads the password from env.
if [ -n "${DJANGO_SUPERUSER_PASSWORD_FILE:-}" ] && [ -z "${DJANGO_SUPERUSER_PASSWORD:-}" ]; then
    DJANGO_SUPERUSER_PASSWORD=$(cat "$DJANGO_SUPERUSER_PASSWORD_FILE")
    export DJANGO_SUPERUSER_PASSWORD
fi
cmd=${1:-daphne}
[ $# -gt 0 ] && shift
case $cmd in
    daphne)
        python3 migrate_locked.py
        exec scripts/daphne -b 0.0.0.0 -p 8000 --proxy-headers "$@" ;;
    worker)
        python3 migrate_locked.py
        exec celery -A bridgeos_cloud worker -l "${LOG_LEVEL:-info}" -c "${BRIDGEOS_WORKER_CONCURRENCY:-2}" "$@" ;;
    beat)
        exec celery -A bridgeos_cloud beat -l "${LOG_LEVEL:-info}" --schedule /var/lib/bridgeos/celerybeat-schedule "$@" ;;
    migrate)
        exec python3 migrate_locked.py "$@" ;;
    manage)
        exec python3 manage.py "$@" ;;
    health)
        exec python3 -c 'import urllib.request; urllib.request.urlopen("http://127.0.0.1:8000/api/health", timeout=3)' ;;
    *)
        echo "bridgeos-cloud: unknown subcommand $cmd (daphne, worker, beat, migrate, manage, health)" >&2
        exit 2 ;;
esac

#!/bin/sh
# Initialise $PGDATA on first start (superuser postgres, database $POSTGRES_DB, password from
# POSTGRES_PASSWORD_FILE, password auth over the network), then run PostgreSQL in the foreground.
set -eu
: "${POSTGRES_DB:=bridgeos}"
if [ ! -s "$PGDATA/PG_VERSION" ]; then
    [ -r "${POSTGRES_PASSWORD_FILE:-}" ] || { echo "bridgeos-postgres: POSTGRES_PASSWORD_FILE must name a readable file" >&2; exit 2; }
    # The password file may lack a trailing newline; initdb reads its first line.
    initdb -U postgres -E UTF8 --locale=C.UTF-8 --auth-local=peer --auth-host=scram-sha-256 \
        --pwfile="$POSTGRES_PASSWORD_FILE" >/dev/null
    echo "host all all 0.0.0.0/0 scram-sha-256" >>"$PGDATA/pg_hba.conf"
    echo "host all all ::/0 scram-sha-256" >>"$PGDATA/pg_hba.conf"
    # Started on the socket only, so nobody connects before the database exists.
    pg_ctl -D "$PGDATA" -o "-c listen_addresses=''" -w start >/dev/null
    createdb -U postgres "$POSTGRES_DB"
    pg_ctl -D "$PGDATA" -m fast -w stop >/dev/null
    echo "bridgeos-postgres: initialised $PGDATA with database $POSTGRES_DB"
fi
exec postgres -D "$PGDATA" -c listen_addresses='*' -c max_connections="${POSTGRES_MAX_CONNECTIONS:-200}" "$@"

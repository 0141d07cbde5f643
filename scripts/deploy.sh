#!/usr/bin/env bash
# Deploy bridgeOS Cloud as a Docker Swarm stack on this machine (docker/stack.yml), or remove it.
#
#   scripts/deploy.sh                 # `make deploy`: build images, write secrets, deploy, wait, print the login
#   scripts/deploy.sh down            # `make undeploy`: remove the stack, keep its volumes
#   scripts/deploy.sh down --volumes  # ... and delete its PostgreSQL and Redis volumes too
#
# Environment: BRIDGEOS_STACK (stack name, default bridgeos), BRIDGEOS_HTTP_PORT (the load balancer's
# host port, default 8080), DAPHNE_REPLICAS (2), WORKER_REPLICAS (1), BRIDGEOS_SECRETS_DIR (default
# .data/deploy/STACK/secrets), BRIDGEOS_DEPLOY_WAIT_S (how long to wait for health, default 300).
set -euo pipefail
ROOT_DIR="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
STACK=${BRIDGEOS_STACK:-bridgeos}
export BRIDGEOS_HTTP_PORT=${BRIDGEOS_HTTP_PORT:-8080}
export BRIDGEOS_SECRETS_DIR=${BRIDGEOS_SECRETS_DIR:-$ROOT_DIR/.data/deploy/$STACK/secrets}
export DAPHNE_REPLICAS=${DAPHNE_REPLICAS:-2}
export WORKER_REPLICAS=${WORKER_REPLICAS:-1}
WAIT_S=${BRIDGEOS_DEPLOY_WAIT_S:-300}
# The serving path must be healthy before the URL is printed; Celery's parts need only be running
# (the worker's health check pings it through the broker every 30 s, the first time 30 s after start).
HEALTHY=(postgres redis daphne lb)
RUNNING=(worker beat)

say() { printf '%s\n' "deploy: $*"; }
die() { printf '%s\n' "deploy: $*" >&2; exit 1; }

undeploy() {  # [--volumes]
    # Always asked, even when no service is listed: a deploy that failed half-way leaves secrets and networks.
    docker stack rm "$STACK" >/dev/null 2>&1 || true
    # Tasks and the network go asynchronously; volumes can be removed only once containers are gone.
    local deadline=$((SECONDS + 60))
    while docker ps -aq --filter "label=com.docker.stack.namespace=$STACK" | grep -q . ||
          docker network ls -q --filter "label=com.docker.stack.namespace=$STACK" | grep -q .; do
        ((SECONDS < deadline)) || die "stack $STACK still has containers or networks after 60 s"
        sleep 1
    done
    say "removed stack $STACK"
    if [[ ${1:-} == --volumes ]]; then
        local volumes; volumes=$(docker volume ls -q --filter "label=com.docker.stack.namespace=$STACK")
        [[ -z $volumes ]] || docker volume rm $volumes >/dev/null
        rm -rf "$BRIDGEOS_SECRETS_DIR"
        say "removed its volumes${volumes:+ (${volumes//$'\n'/ })} and secrets"
    else
        say "volumes kept (scripts/deploy.sh down --volumes deletes them)"
    fi
}

write_secret() {  # name, generator command...
    local file="$BRIDGEOS_SECRETS_DIR/$1"; shift
    [[ -s $file ]] && return
    (umask 077 && "$@" >"$file")
}
random_token() { head -c 32 /dev/urandom | base64 | tr -d '/+=\n' | head -c 40; }
fernet_key() { head -c 32 /dev/urandom | base64 | tr '+/' '-_'; }

replicas_ready() {  # service [running]: every wanted task healthy (or, with "running", started)
    local svc="${STACK}_$1" want running
    want=$(docker service inspect --format '{{if .Spec.Mode.Replicated}}{{.Spec.Mode.Replicated.Replicas}}{{end}}' "$svc")
    running=0
    local cid
    for cid in $(docker ps -q --filter "label=com.docker.swarm.service.name=$svc"); do
        local health
        health=$(docker inspect --format '{{if .State.Health}}{{.State.Health.Status}}{{else}}running{{end}}' "$cid")
        [[ $health == healthy || $health == running || ($2 == running && $health == starting) ]] &&
            running=$((running + 1))
    done
    [[ $running -ge $want ]]
}

lb_answers() {
    (exec 3<>"/dev/tcp/127.0.0.1/$BRIDGEOS_HTTP_PORT" &&
        printf 'GET /api/health HTTP/1.0\r\nHost: localhost\r\n\r\n' >&3 && head -1 <&3 | grep -q ' 200 ') 2>/dev/null
}

pin_images() {  # tag each stack image by its inputs and point the stack at those tags
    # A service whose image tag did not change is left alone by `docker stack deploy`; a tag naming
    # the image's inputs changes with them, so deploying new code rolls the replicas (update_config).
    local var image inputs
    for var in CLOUD:bridgeos/cloud:latest POSTGRES:bridgeos/postgres:15 REDIS:bridgeos/redis:7 HAPROXY:bridgeos/haproxy:2.6; do
        image=${var#*:}
        inputs=$(docker image inspect --format '{{index .Config.Labels "org.bridgeos.inputs"}}' "$image")
        docker tag "$image" "${image%:*}:in-${inputs:0:12}"
        export "BRIDGEOS_${var%%:*}_IMAGE=${image%:*}:in-${inputs:0:12}"
    done
}

deploy() {
    [[ $(docker info --format '{{.Swarm.LocalNodeState}}' 2>/dev/null) == active ]] ||
        die "this machine is not in a Swarm: scripts/services.sh swarm"
    bash "$ROOT_DIR/docker/build-images.sh" stack
    pin_images
    mkdir -p "$BRIDGEOS_SECRETS_DIR"
    chmod 700 "$BRIDGEOS_SECRETS_DIR"
    write_secret db_password random_token
    write_secret secret_key random_token
    write_secret pki_key fernet_key
    write_secret operator_password random_token
    local t=$SECONDS
    docker stack deploy --prune -c "$ROOT_DIR/docker/stack.yml" "$STACK" >/dev/null
    say "stack $STACK deployed (daphne x$DAPHNE_REPLICAS, worker x$WORKER_REPLICAS); waiting for it to be healthy"
    local deadline=$((SECONDS + WAIT_S)) svc pending
    while :; do
        pending=()
        for svc in "${HEALTHY[@]}"; do replicas_ready "$svc" healthy || pending+=("$svc"); done
        for svc in "${RUNNING[@]}"; do replicas_ready "$svc" running || pending+=("$svc"); done
        if ((${#pending[@]} == 0)) && lb_answers; then break; fi
        if ((SECONDS > deadline)); then
            docker stack ps --no-trunc "$STACK" >&2 || true
            die "not healthy within $WAIT_S s (waiting for: ${pending[*]:-the load balancer})"
        fi
        sleep 2
    done
    say "healthy after $((SECONDS - t)) s"
    echo "bridgeOS Cloud: http://127.0.0.1:$BRIDGEOS_HTTP_PORT/   (robots: ws://HOST:$BRIDGEOS_HTTP_PORT)"
    echo "Operator login: operator / $(cat "$BRIDGEOS_SECRETS_DIR/operator_password")"
}

case ${1:-up} in
    up) deploy ;;
    down) shift; undeploy "$@" ;;
    *) die "unknown command $1 (up, down [--volumes])" ;;
esac

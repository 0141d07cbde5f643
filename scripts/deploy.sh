#!/usr/bin/env bash
# Deploy bridgeOS Cloud as a Docker Swarm stack on this machine (docker/stack.yml), or remove it.
#
#   scripts/deploy.sh                 # `make deploy`: build images, write secrets, deploy, push the images to
#                                     # the stack's registry, deploy them by digest, wait, print the login
#   scripts/deploy.sh down            # `make undeploy`: remove the stack, keep its volumes
#   scripts/deploy.sh down --volumes  # ... and delete its PostgreSQL and Redis volumes too
#
# Environment: BRIDGEOS_STACK (stack name, default bridgeos), BRIDGEOS_HTTPS_PORT (the load balancer's
# TLS port, default 8443), BRIDGEOS_HTTP_PORT (its plain HTTP port, which redirects there, default 8080),
# BRIDGEOS_DEPLOY_NAMES (the names and addresses browsers and robots reach the stack by, comma-separated,
# default this host's name, BRIDGEOS_CLOUD_ADDRESS, localhost and 127.0.0.1; the first is the one printed),
# BRIDGEOS_DEPLOY_TLS_CERT and BRIDGEOS_DEPLOY_TLS_KEY (PEM files: the TLS certificate chain and key the
# load balancer serves; without them, one is issued from the cloud's CA for BRIDGEOS_DEPLOY_NAMES),
# DAPHNE_REPLICAS (2), WORKER_REPLICAS (1), BRIDGEOS_SECRETS_DIR (default
# .data/deploy/STACK/secrets), BRIDGEOS_DEPLOY_WAIT_S (how long to wait for health, default 300),
# BRIDGEOS_REGISTRY_PORT (the registry's host port, default 5443: `make run`'s registry keeps 5000),
# BRIDGEOS_REGISTRY_NAMES (names and addresses its TLS certificate carries, comma-separated, default
# this host's name and 127.0.0.1; the first names it in image references), BRIDGEOS_CLOUD_ADDRESS
# (where cloud copies reach the load balancer, default this host's first address),
# BRIDGEOS_CLOUD_VOLUMES_DIR (host directory of cloud copies' volumes, default .data/deploy/STACK/volumes),
# BRIDGEOS_STACK_PLACEMENT (a placement constraint for the cloud's services, default any Linux node),
# BRIDGEOS_DEPLOY_ROS_IMAGES (1: push bridgeos/ros and bridgeos/ros2 too when built here; 0: not).
set -euo pipefail
ROOT_DIR="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
STACK=${BRIDGEOS_STACK:-bridgeos}
export BRIDGEOS_STACK=$STACK
# Plain HTTP on the first port is redirected to TLS on the second; robots and browsers use the second.
export BRIDGEOS_HTTP_PORT=${BRIDGEOS_HTTP_PORT:-8080}
export BRIDGEOS_HTTPS_PORT=${BRIDGEOS_HTTPS_PORT:-8443}
# The operator's certificate chain and key for the TLS port (PEM files); without them the cloud's CA issues one.
TLS_CERT=${BRIDGEOS_DEPLOY_TLS_CERT:-}
TLS_KEY=${BRIDGEOS_DEPLOY_TLS_KEY:-}
export BRIDGEOS_SECRETS_DIR=${BRIDGEOS_SECRETS_DIR:-$ROOT_DIR/.data/deploy/$STACK/secrets}
export DAPHNE_REPLICAS=${DAPHNE_REPLICAS:-2}
export WORKER_REPLICAS=${WORKER_REPLICAS:-1}
WAIT_S=${BRIDGEOS_DEPLOY_WAIT_S:-300}
export BRIDGEOS_REGISTRY_PORT=${BRIDGEOS_REGISTRY_PORT:-5443}
REGISTRY_NAMES=${BRIDGEOS_REGISTRY_NAMES:-$(hostname),127.0.0.1}
IFS=, read -r -a REGISTRY_NAME_LIST <<<"$REGISTRY_NAMES"
export BRIDGEOS_REGISTRY_HOST="${REGISTRY_NAME_LIST[0]}:$BRIDGEOS_REGISTRY_PORT"
first_address() { hostname -I 2>/dev/null | awk '{print $1}'; }
export BRIDGEOS_CLOUD_ADDRESS=${BRIDGEOS_CLOUD_ADDRESS:-$(first_address)}
# What browsers and robots call the stack: its certificate, allowed hosts and CSRF origins carry these names.
# Not every address of `hostname -I`: Docker's bridges are among them and come and go, which would issue a new
# certificate (and restart the load balancer) on the next deploy.
DEPLOY_NAMES=${BRIDGEOS_DEPLOY_NAMES:-$(hostname),$BRIDGEOS_CLOUD_ADDRESS,localhost,127.0.0.1}
# Each name once, in the order given.
IFS=, read -r -a DEPLOY_NAME_LIST <<<"$(tr ',' '\n' <<<"$DEPLOY_NAMES" | sed 's/^ *//; s/ *$//' | awk 'NF && !seen[$0]++' | paste -sd, -)"
# Labels the cloud copies, ROS masters and robot networks the stack's worker makes; the default (from the
# database's address, the same in every stack) would let two stacks on one Swarm take each other's for strays.
export BRIDGEOS_CLOUD_ID=${BRIDGEOS_CLOUD_ID:-$STACK}
export BRIDGEOS_CLOUD_VOLUMES_DIR=${BRIDGEOS_CLOUD_VOLUMES_DIR:-$ROOT_DIR/.data/deploy/$STACK/volumes}
# The docker CLI's login to the stack's registry stays with the stack, not in the operator's ~/.docker.
export DOCKER_CONFIG=${BRIDGEOS_DEPLOY_DOCKER_CONFIG:-$BRIDGEOS_SECRETS_DIR/docker}
# Images pushed to the stack's registry (the registry's own image stays local: it cannot pull itself).
PUSHED=(CLOUD:bridgeos/cloud POSTGRES:bridgeos/postgres REDIS:bridgeos/redis HAPROXY:bridgeos/haproxy)
# The images of the cloud's per-robot ROS masters and ROS 2 discovery servers, pushed too when built here.
PUSH_ROS=${BRIDGEOS_DEPLOY_ROS_IMAGES:-1}
# The serving path must be healthy before the URL is printed; Celery's parts need only be running
# (the worker's health check pings it through the broker every 30 s, the first time 30 s after start).
HEALTHY=(postgres redis daphne lb registry docker-proxy)
RUNNING=(worker beat)

say() { printf '%s\n' "deploy: $*"; }
die() { printf '%s\n' "deploy: $*" >&2; exit 1; }

remove_stack() {  # remove the stack's services and wait until its containers and network are gone
    # Always asked, even when no service is listed: a deploy that failed half-way leaves secrets and networks.
    docker stack rm "$STACK" >/dev/null 2>&1 || true
    # Tasks and the network go asynchronously; volumes can be removed only once containers are gone.
    local deadline=$((SECONDS + 60))
    while docker ps -aq --filter "label=com.docker.stack.namespace=$STACK" | grep -q . ||
          docker network ls -q --filter "label=com.docker.stack.namespace=$STACK" | grep -q .; do
        ((SECONDS < deadline)) || die "stack $STACK still has containers or networks after 60 s"
        sleep 1
    done
}

undeploy() {  # [--volumes]
    # What the stack's worker made lives outside the stack: its cloud copies and robot networks go first.
    local made
    made=$(docker service ls -q --filter "label=io.bridgeos.cloud=$BRIDGEOS_CLOUD_ID")
    [[ -z $made ]] || docker service rm $made >/dev/null
    remove_stack
    made=$(docker network ls -q --filter "label=io.bridgeos.cloud=$BRIDGEOS_CLOUD_ID")
    [[ -z $made ]] || docker network rm $made >/dev/null 2>&1 || say "some robot networks are still in use: $made"
    say "removed stack $STACK"
    if [[ ${1:-} == --volumes ]]; then
        local volumes; volumes=$(docker volume ls -q --filter "label=com.docker.stack.namespace=$STACK")
        [[ -z $volumes ]] || docker volume rm $volumes >/dev/null
        untrust_registry
        rm -rf "$BRIDGEOS_SECRETS_DIR" "$BRIDGEOS_CLOUD_VOLUMES_DIR"
        say "removed its volumes${volumes:+ (${volumes//$'\n'/ })}, secrets and cloud copies' volumes"
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
    local svc="${STACK}_$1" want running update
    want=$(docker service inspect --format '{{if .Spec.Mode.Replicated}}{{.Spec.Mode.Replicated.Replicas}}{{end}}' "$svc")
    # A rolling update counts the old replicas as healthy: wait until it is over.
    update=$(docker service inspect --format '{{if .UpdateStatus}}{{.UpdateStatus.State}}{{end}}' "$svc")
    [[ $update != updating && $update != rollback_started ]] || return 1
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

lb_answers() {  # the cloud answers through the load balancer's TLS port (verified when its CA is the cloud's)
    local verify=(--cacert "$BRIDGEOS_SECRETS_DIR/ca.crt")
    [[ -z $TLS_CERT ]] || verify=(--insecure)  # liveness only: robots verify it themselves
    local name=${DEPLOY_NAME_LIST[0]}
    curl -fsS -o /dev/null --max-time 5 "${verify[@]}" --resolve "$name:$BRIDGEOS_HTTPS_PORT:127.0.0.1" \
        "https://$name:$BRIDGEOS_HTTPS_PORT/api/health" 2>/dev/null
}

pin_images() {  # tag each stack image by its inputs and point the stack at those tags
    # A service whose image tag did not change is left alone by `docker stack deploy`; a tag naming
    # the image's inputs changes with them, so deploying new code rolls the replicas (update_config).
    local var image inputs
    for var in CLOUD:bridgeos/cloud:latest POSTGRES:bridgeos/postgres:15 REDIS:bridgeos/redis:7 \
        HAPROXY:bridgeos/haproxy:2.6 REGISTRY:bridgeos/registry:2.8; do
        image=${var#*:}
        inputs=$(docker image inspect --format '{{index .Config.Labels "org.bridgeos.inputs"}}' "$image")
        docker tag "$image" "${image%:*}:in-${inputs:0:12}"
        export "BRIDGEOS_${var%%:*}_IMAGE=${image%:*}:in-${inputs:0:12}"
    done
}

pin_ros_images() {  # the ROS images cloud copies' masters run from, when this machine has them
    [[ $PUSH_ROS == 1 ]] || return 0
    local var image inputs
    for var in CLOUD_ROS:bridgeos/ros:noetic CLOUD_ROS2:bridgeos/ros2:jazzy; do
        image=${var#*:}
        inputs=$(docker image inspect --format '{{index .Config.Labels "org.bridgeos.inputs"}}' "$image" 2>/dev/null) ||
            { say "$image is not built here: not pushed (docker/build-images.sh ${image#bridgeos/})"; continue; }
        docker tag "$image" "${image%:*}:in-${inputs:0:12}"
        export "BRIDGEOS_${var%%:*}_IMAGE=${image%:*}:in-${inputs:0:12}"
        PUSHED+=("${var%%:*}:${image%:*}")
    done
}

in_cloud_image() {  # command...: run in a throwaway cloud container with the secrets directory as /run/secrets
    docker run --rm --network none --user "$(id -u):$(id -g)" --entrypoint "" \
        -v "$BRIDGEOS_SECRETS_DIR:/run/secrets" -e BRIDGEOS_DATA_DIR=/tmp/bridgeos \
        -e SECRET_KEY_FILE=/run/secrets/secret_key -e BRIDGEOS_PKI_KEY_FILE=/run/secrets/pki_key \
        -e BRIDGEOS_REGISTRY_KEY_FILE=/run/secrets/registry_key "$BRIDGEOS_CLOUD_IMAGE" "$@"
}

tls_files() {  # the CA, the registry's certificate and token key, the lb's PEM; its config.yml (each once)
    rm -f "$BRIDGEOS_SECRETS_DIR/lb_given.crt" "$BRIDGEOS_SECRETS_DIR/lb_given.key"
    if [[ -n $TLS_CERT$TLS_KEY ]]; then
        [[ -n $TLS_CERT && -n $TLS_KEY ]] ||
            die "give both BRIDGEOS_DEPLOY_TLS_CERT and BRIDGEOS_DEPLOY_TLS_KEY, or neither (the cloud's CA issues one)"
        [[ -r $TLS_CERT ]] || die "BRIDGEOS_DEPLOY_TLS_CERT=$TLS_CERT: no such readable file"
        [[ -r $TLS_KEY ]] || die "BRIDGEOS_DEPLOY_TLS_KEY=$TLS_KEY: no such readable file"
        (umask 077 && cp "$TLS_CERT" "$BRIDGEOS_SECRETS_DIR/lb_given.crt" && cp "$TLS_KEY" "$BRIDGEOS_SECRETS_DIR/lb_given.key")
    fi
    local names="${DEPLOY_NAME_LIST[*]}"
    CA_FINGERPRINT=$(in_cloud_image python3 stack_pki.py /run/secrets --lb-names "${names// /,}" \
        "${REGISTRY_NAME_LIST[@]}" registry) || die "making the stack's certificates failed"
    rm -f "$BRIDGEOS_SECRETS_DIR/lb_given.crt" "$BRIDGEOS_SECRETS_DIR/lb_given.key"
    export BRIDGEOS_LB_PEM_HASH; BRIDGEOS_LB_PEM_HASH=$(sha256sum "$BRIDGEOS_SECRETS_DIR/lb.pem" | cut -c1-12)
    local realm="https://${DEPLOY_NAME_LIST[0]}:$BRIDGEOS_HTTPS_PORT/api/registry/token"
    if [[ -s $BRIDGEOS_SECRETS_DIR/config.yml ]] && ! grep -qF "realm: \"$realm\"" "$BRIDGEOS_SECRETS_DIR/config.yml"; then
        die "the registry's config.yml names another token realm than $realm: to change it, run" \
            "scripts/deploy.sh down, delete $BRIDGEOS_SECRETS_DIR/config.yml, and deploy again"
    fi
    # Written once: its http secret must stay what the running registry has (Swarm secrets are immutable).
    [[ -s $BRIDGEOS_SECRETS_DIR/config.yml ]] ||
        in_cloud_image python3 manage.py registry_config \
            --realm "$realm" \
            --listen 0.0.0.0:5000 --storage /var/lib/docker-registry --out /run/secrets \
            --tls-cert /run/secrets/registry_tls.crt --tls-key /run/secrets/registry_tls.key \
            --notify http://daphne:8000/api/registry/events >/dev/null
}

registry_doors() {  # print each NAME:PORT the registry answers at with a certificate from the cloud's CA
    local name
    for name in "${REGISTRY_NAME_LIST[@]}"; do echo "$name:$BRIDGEOS_REGISTRY_PORT"; done
    # Behind the load balancer (/v2/) too, when its certificate is the CA's (an operator's is trusted as such).
    if [[ -z $TLS_CERT ]]; then
        for name in "${DEPLOY_NAME_LIST[@]}"; do [[ $name == *:* ]] || echo "$name:$BRIDGEOS_HTTPS_PORT"; done
    fi
}

trust_registry() {  # this engine trusts the registry's certificate through certs.d (robots: see the docs)
    local door dir
    for door in $(registry_doors); do
        dir=/etc/docker/certs.d/$door
        if ! { mkdir -p "$dir" && cp "$BRIDGEOS_SECRETS_DIR/ca.crt" "$dir/ca.crt"; } 2>/dev/null; then
            die "cannot write $dir/ca.crt (run as root, or copy $BRIDGEOS_SECRETS_DIR/ca.crt there yourself)"
        fi
    done
}

untrust_registry() {  # forget what trust_registry installed, if it is still this stack's CA
    local door dir
    for door in $(registry_doors); do
        dir=/etc/docker/certs.d/$door
        if [[ -f $BRIDGEOS_SECRETS_DIR/ca.crt ]] && cmp -s "$dir/ca.crt" "$BRIDGEOS_SECRETS_DIR/ca.crt"; then
            rm -f "$dir/ca.crt" && rmdir "$dir" 2>/dev/null || true
        fi
    done
}

wait_healthy() {
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
}

rolled_back() {  # print the services whose spec is not the image just deployed (Swarm rolled them back)
    local svc var image
    for svc in daphne:CLOUD worker:CLOUD beat:CLOUD docker-proxy:CLOUD postgres:POSTGRES redis:REDIS lb:HAPROXY \
        registry:REGISTRY; do
        var="BRIDGEOS_${svc#*:}_IMAGE"
        image=$(docker service inspect --format '{{.Spec.TaskTemplate.ContainerSpec.Image}}' "${STACK}_${svc%%:*}")
        [[ $image == "${!var}"* ]] || printf '%s ' "${svc%%:*}"
    done
}

stack_serving() {  # the stack runs its registry and answers through the load balancer
    docker service inspect "${STACK}_registry" >/dev/null 2>&1 && replicas_ready registry healthy && lb_answers
}

push_images() {  # push the stack's images to its registry as the operator; point the stack at their digests
    docker login "$BRIDGEOS_REGISTRY_HOST" -u operator --password-stdin \
        <"$BRIDGEOS_SECRETS_DIR/operator_password" >/dev/null ||
        die "docker login $BRIDGEOS_REGISTRY_HOST as operator failed"
    local var local_ref remote digest failed=0
    declare -A pushes=()
    # Side by side: each push waits mostly on compressing and writing its own layers.
    for var in "${PUSHED[@]}"; do
        local_ref=$(printenv "BRIDGEOS_${var%%:*}_IMAGE")
        remote="$BRIDGEOS_REGISTRY_HOST/${var#*:}:${local_ref##*:}"
        docker tag "$local_ref" "$remote"
        docker push -q "$remote" >/dev/null &
        pushes[$var]="$! $remote"
    done
    for var in "${PUSHED[@]}"; do
        remote=${pushes[$var]#* }
        wait "${pushes[$var]%% *}" || { say "docker push $remote failed" >&2; failed=1; continue; }
        digest=$(docker image inspect --format '{{range .RepoDigests}}{{println .}}{{end}}' "$remote" |
            grep -m1 "^$BRIDGEOS_REGISTRY_HOST/${var#*:}@") || die "no digest of $remote after its push"
        export "BRIDGEOS_${var%%:*}_IMAGE=$digest"
    done
    ((failed == 0)) || die "pushing the stack's images to $BRIDGEOS_REGISTRY_HOST failed"
    say "images pushed to $BRIDGEOS_REGISTRY_HOST (${PUSHED[*]#*:}) in $((SECONDS - pushing)) s"
}

deploy() {
    [[ $(docker info --format '{{.Swarm.LocalNodeState}}' 2>/dev/null) == active ]] ||
        die "this machine is not in a Swarm: scripts/services.sh swarm"
    [[ -n $BRIDGEOS_CLOUD_ADDRESS ]] ||
        die "this host has no address for cloud copies to reach the cloud at: set BRIDGEOS_CLOUD_ADDRESS"
    bash "$ROOT_DIR/docker/build-images.sh" stack
    pin_images
    pin_ros_images
    mkdir -p "$BRIDGEOS_SECRETS_DIR" "$DOCKER_CONFIG" "$BRIDGEOS_CLOUD_VOLUMES_DIR"
    chmod 700 "$BRIDGEOS_SECRETS_DIR" "$DOCKER_CONFIG"
    # The cloud (uid 10000 in its image) makes one directory per cloud copy's volume in it.
    chown 10000:10000 "$BRIDGEOS_CLOUD_VOLUMES_DIR" 2>/dev/null || chmod 1777 "$BRIDGEOS_CLOUD_VOLUMES_DIR"
    write_secret db_password random_token
    write_secret secret_key random_token
    write_secret pki_key fernet_key
    write_secret operator_password random_token
    tls_files
    trust_registry
    export BRIDGEOS_REGISTRY_NODE; BRIDGEOS_REGISTRY_NODE=$(docker info --format '{{.Swarm.NodeID}}')
    local names="${REGISTRY_NAME_LIST[*]}" name hosts="" origins=""
    for name in "${DEPLOY_NAME_LIST[@]}"; do
        [[ $name != *:* ]] || name="[$name]"  # an IPv6 address, as Host headers and URLs carry it
        hosts+=",$name"
        origins+=",https://$name:$BRIDGEOS_HTTPS_PORT"
        [[ $BRIDGEOS_HTTPS_PORT != 443 ]] || origins+=",https://$name"
    done
    # Loopback too, whatever the names: the lb's health checks and this script ask by it.
    export ALLOWED_HOSTS=${ALLOWED_HOSTS:-127.0.0.1,localhost,daphne,$BRIDGEOS_CLOUD_ADDRESS,${names// /,}$hosts}
    export CSRF_TRUSTED_ORIGINS=${CSRF_TRUSTED_ORIGINS:-${origins#,}}
    local t=$SECONDS
    # The images are pushed through the stack itself (its registry, its token realm): the first time, it
    # starts from this machine's local images; later deploys push to the stack that is running.
    local fresh=""
    docker service ls -q --filter "label=com.docker.stack.namespace=$STACK" | grep -q . || fresh=1
    if ! stack_serving; then
        docker stack deploy --prune -c "$ROOT_DIR/docker/stack.yml" "$STACK" >/dev/null
        say "stack $STACK deployed from local images; waiting for its registry and cloud"
        wait_healthy
        say "serving from local images after $((SECONDS - t)) s"
    fi
    local pushing=$SECONDS
    push_images
    if [[ -n $fresh ]]; then
        # Nobody uses a stack deployed a minute ago: starting it again from the registry's images (the
        # same bytes; its volumes, the migrated database and the pushed images, stay) is quicker than
        # a rolling update paced for serving robots.
        remove_stack
        say "stack $STACK removed to start again from its registry's images"
    fi
    docker stack deploy --prune --with-registry-auth -c "$ROOT_DIR/docker/stack.yml" "$STACK" >/dev/null
    say "stack $STACK deployed from $BRIDGEOS_REGISTRY_HOST (daphne x$DAPHNE_REPLICAS, worker x$WORKER_REPLICAS);" \
        "waiting for it to be healthy"
    wait_healthy
    local back; back=$(rolled_back)
    [[ -z $back ]] || die "Swarm rolled back ${back% } (its new tasks failed: docker service ps --no-trunc ${STACK}_${back%% *})"
    say "healthy after $((SECONDS - t)) s"
    local public="${DEPLOY_NAME_LIST[0]}:$BRIDGEOS_HTTPS_PORT"
    [[ ${DEPLOY_NAME_LIST[0]} != *:* ]] || public="[${DEPLOY_NAME_LIST[0]}]:$BRIDGEOS_HTTPS_PORT"
    echo "bridgeOS Cloud: https://$public/   (plain http://…:$BRIDGEOS_HTTP_PORT/ redirects there)"
    if [[ -n $TLS_CERT ]]; then
        echo "TLS: the certificate of $TLS_CERT; robots verify it with the system's CAs, or --ca with the CA that issued it"
        echo "Robots: bridgeos-agent run --master wss://$public --robot ID --token TOKEN"
    else
        echo "TLS: a certificate from the cloud's CA for ${DEPLOY_NAME_LIST[*]}"
        echo "Robots: bridgeos-agent run --master wss://$public --ca $BRIDGEOS_SECRETS_DIR/ca.crt --robot ID --token TOKEN"
    fi
    echo "Image registry: $BRIDGEOS_REGISTRY_HOST, and https://$public/v2/ (TLS from the cloud's CA; docker login with a user's password or API token)"
    echo "The cloud's CA ($BRIDGEOS_SECRETS_DIR/ca.crt), SHA-256 fingerprint $CA_FINGERPRINT,"
    echo "for robots' engines (/etc/docker/certs.d/$BRIDGEOS_REGISTRY_HOST/ca.crt) and bridgeos-agent --ca:"
    cat "$BRIDGEOS_SECRETS_DIR/ca.crt"
    echo "Operator login: operator / $(cat "$BRIDGEOS_SECRETS_DIR/operator_password")"
}

case ${1:-up} in
    up) deploy ;;
    down) shift; undeploy "$@" ;;
    *) die "unknown command $1 (up, down [--volumes])" ;;
esac

#!/usr/bin/env bash
# Build the local bridgeOS images, skipping each one whose inputs have not changed.
#
#   docker/build-images.sh          # the images the tests use: base, ros and ros2
#   docker/build-images.sh ros      # one image (and, first, what it is built on)
#   docker/build-images.sh ros2     # ROS 2 Jazzy from the PyPI wheels (cloud copies, discovery servers)
#   docker/build-images.sh stack    # what docker/stack.yml runs: cloud agent postgres redis haproxy registry
#
# No registry is reachable, so everything starts from a debootstrapped Debian base.
# Each image carries the label org.bridgeos.inputs = sha256 of what it is made from
# (its files, plus its parent's image id); an image whose label matches is not rebuilt.
# To add an image: write image_<name>() with build_image, and append <name> to IMAGES.
set -euo pipefail

DOCKER_DIR="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
IMAGES=(base ros ros2 python cloud agent postgres redis haproxy registry)
# Built only when asked (scripts/deploy.sh, the deploy test): CI's services.sh builds base, ros and ros2
# (ros2 for the Swarm test of a ROS 2 cloud copy: about 3 minutes once, then skipped while unchanged).
DEFAULT_IMAGES=(base ros ros2)
STACK_IMAGES=(cloud agent postgres redis haproxy registry)
LABEL=org.bridgeos.inputs
LOG_DIR=${BRIDGEOS_LOG_DIR:-/var/log}
# The classic builder runs in the daemon itself: no buildx plugin needed on the host.
export DOCKER_BUILDKIT=0

now() { date +%s.%N; }
elapsed() { awk -v s="$1" -v e="$(now)" 'BEGIN { printf "%.1fs", e - s }'; }

inputs_hash() {  # extra-text, paths under docker/ ...
    local extra=$1; shift
    {
        printf '%s\n' "$extra"
        (cd "$DOCKER_DIR" && find "$@" -type f -not -path '*/__pycache__/*' -print0 | LC_ALL=C sort -z | xargs -0 sha256sum)
    } | sha256sum | cut -c1-64
}

image_label() { docker image inspect --format "{{index .Config.Labels \"$LABEL\"}}" "$1" 2>/dev/null || true; }
image_id() { docker image inspect --format '{{.Id}}' "$1"; }

declare -A DONE=()
build_image() {  # tag, inputs hash, builder command...
    local tag=$1 hash=$2; shift 2
    local t; t=$(now)
    if [[ $(image_label "$tag") == "$hash" ]]; then
        echo "image $tag: up to date (inputs ${hash:0:12}) [$(elapsed "$t")]"
        return
    fi
    echo "image $tag: building (inputs ${hash:0:12}) ..."
    "$@" "$tag" "$hash"
    echo "image $tag: built [$(elapsed "$t")]"
}

docker_build() {  # context dir (under docker/, or absolute), tag, hash
    local log="$LOG_DIR/bridgeos-image-${2//[:\/]/-}.log" context=$1
    [[ $context == /* ]] || context="$DOCKER_DIR/$context"
    if ! docker build --network host --label "$LABEL=$3" -t "$2" "$context" >"$log" 2>&1; then
        echo "image $2: docker build failed, last lines of $log:" >&2
        tail -20 "$log" >&2
        return 1
    fi
    grep '^Step ' "$log" | sed 's/^/    /' || true
}

image_base() {
    build_image bridgeos/base:bookworm "$(inputs_hash "" base)" \
        bash "$DOCKER_DIR/base/mkimage.sh"
}

# The use-case nodes live in the agent package; the ros image carries only them (stdlib, rospy, numpy).
USECASES=../agent/src/bridgeos_agent/usecases
AGENT_INIT=../agent/src/bridgeos_agent/__init__.py
AGENT_ROS2GRAPH=../agent/src/bridgeos_agent/ros2graph.py

stage_usecases() {  # context dir, command name, module: the use-case nodes and a command starting them
    mkdir -p "$1/usecases/bridgeos/bridgeos_agent"
    cp "$DOCKER_DIR/$AGENT_INIT" "$1/usecases/bridgeos/bridgeos_agent/"
    (cd "$DOCKER_DIR/$USECASES/.." && find usecases -type f -name '*.py' -not -path '*/__pycache__/*' \
        -exec cp --parents {} "$1/usecases/bridgeos/bridgeos_agent/" \;)
    # What the ROS 2 nodes take from the agent beyond the use cases: rclpy_missing (standard library only).
    cp "$DOCKER_DIR/$AGENT_ROS2GRAPH" "$1/usecases/bridgeos/bridgeos_agent/"
    printf '#!/bin/sh\n# Start a bridgeOS use-case node: %s NODE [ARGS]\n%s\n' "$2" \
        "PYTHONPATH=/opt/bridgeos\${PYTHONPATH:+:\$PYTHONPATH} exec python3 -m $3 \"\$@\"" \
        >"$1/usecases/$2"
    chmod 755 "$1/usecases/$2"
}

ros_context() {  # context dir: docker/ros plus the staged use-case nodes
    cp -r "$DOCKER_DIR/ros/." "$1/" && stage_usecases "$1" bridgeos-usecase bridgeos_agent.usecases
}

image_ros() {
    build_image bridgeos/ros:noetic \
        "$(inputs_hash "$(image_id bridgeos/base:bookworm)" ros "$USECASES" "$AGENT_INIT" "$AGENT_ROS2GRAPH")" \
        staged ros_context
}

# ROS 2 Jazzy: a venv with the agent's `ros2` extra (the wheels from PyPI), so a pyproject change
# that touches the extra rebuilds it; the pip CA bundle is staged like bridgeos/python's.
ros2_requirements() {  # agent/pyproject.toml: its `ros2` extra, one a line
    "${PYTHON:-python3}" -c '
import sys, tomllib
with open(sys.argv[1], "rb") as f:
    print("\n".join(tomllib.load(f)["project"]["optional-dependencies"]["ros2"]))' "$1"
}
ros2_context() {
    cp -r "$DOCKER_DIR/ros2/." "$1/" && ros2_requirements "$DOCKER_DIR/../agent/pyproject.toml" >"$1/requirements-ros2.txt" &&
        cp "${PIP_CERT:-${SSL_CERT_FILE:-/etc/ssl/certs/ca-certificates.crt}}" "$1/pip-ca.crt" &&
        stage_usecases "$1" bridgeos-usecase2 bridgeos_agent.usecases.ros2
}
image_ros2() {
    local requirements; requirements=$(ros2_requirements "$DOCKER_DIR/../agent/pyproject.toml")
    build_image bridgeos/ros2:jazzy \
        "$(inputs_hash "$(image_id bridgeos/base:bookworm)$requirements" ros2 "$USECASES" "$AGENT_INIT" "$AGENT_ROS2GRAPH")" \
        staged ros2_context
}

PARENT_base=""
PARENT_ros=base
PARENT_ros2=base

# --- the deployed stack (docker/stack.yml) -------------------------------------------
# bridgeos/python holds Debian's Python and a venv with the agent's dependencies; the agent and
# the cloud build on it, the cloud adding its own dependencies in one more layer. Dependencies are
# listed from the pyproject files, so a code change rebuilds only the layers that copy code.
AGENT_SOURCES=(../agent/pyproject.toml ../agent/src)
# The cloud's Django project and apps: what its image copies, and what decides when it is rebuilt.
CLOUD_TREES=(bridgeos_cloud robots skills monitoring dashboard network recordings registry teams audit rollouts logs templates static)
CLOUD_SOURCES=(../pyproject.toml ../manage.py ../scripts/daphne "${CLOUD_TREES[@]/#/../}")

requirements() {  # pyproject.toml: its [project] dependencies, one a line, without our own packages
    "${PYTHON:-python3}" -c '
import sys, tomllib
with open(sys.argv[1], "rb") as f:
    deps = tomllib.load(f)["project"]["dependencies"]
print("\n".join(d for d in deps if not d.startswith("bridgeos-")))' "$1"
}

stage_agent() {  # context dir: the agent package's pyproject and sources, as agent/
    mkdir -p "$1/agent"
    cp "$DOCKER_DIR/../agent/pyproject.toml" "$1/agent/"
    (cd "$DOCKER_DIR/../agent" && find src -type f -not -path '*/__pycache__/*' -exec cp --parents {} "$1/agent/" \;)
}

python_context() {
    cp -r "$DOCKER_DIR/python/." "$1/" && requirements "$DOCKER_DIR/../agent/pyproject.toml" >"$1/requirements-agent.txt" &&
        cp "${PIP_CERT:-${SSL_CERT_FILE:-/etc/ssl/certs/ca-certificates.crt}}" "$1/pip-ca.crt"
}
agent_context() { cp -r "$DOCKER_DIR/agent/." "$1/" && stage_agent "$1"; }
cloud_context() {
    cp -r "$DOCKER_DIR/cloud/." "$1/" && stage_agent "$1" || return
    requirements "$DOCKER_DIR/../pyproject.toml" >"$1/requirements-cloud.txt" || return
    mkdir -p "$1/src/scripts"
    (cd "$DOCKER_DIR/.." && find manage.py pyproject.toml "${CLOUD_TREES[@]}" \
        -type f -not -path '*/__pycache__/*' -exec cp --parents {} "$1/src/" \;)
    cp "$DOCKER_DIR/../scripts/daphne" "$1/src/scripts/"
}

staged() {  # staging function, tag, hash: build from a temporary context the function fills
    local fill=$1 ctx status=0; shift
    ctx=$(mktemp -d /tmp/bridgeos-context.XXXXXX)
    { "$fill" "$ctx" && docker_build "$ctx" "$@"; } || status=$?
    rm -rf "$ctx"
    return "$status"
}

image_python() {
    build_image bridgeos/python:bookworm \
        "$(inputs_hash "$(image_id bridgeos/base:bookworm)" python ../agent/pyproject.toml)" staged python_context
}
image_agent() {
    build_image bridgeos/agent:latest \
        "$(inputs_hash "$(image_id bridgeos/python:bookworm)" agent "${AGENT_SOURCES[@]}")" staged agent_context
}
image_cloud() {
    build_image bridgeos/cloud:latest \
        "$(inputs_hash "$(image_id bridgeos/python:bookworm)" cloud "${AGENT_SOURCES[@]}" "${CLOUD_SOURCES[@]}")" \
        staged cloud_context
}

# The supporting services come from Debian's packages: there is no registry to pull their images from.
debian_service() {  # name, tag
    build_image "$2" "$(inputs_hash "$(image_id bridgeos/base:bookworm)" "$1")" docker_build "$1"
}
image_postgres() { debian_service postgres bridgeos/postgres:15; }
image_redis() { debian_service redis bridgeos/redis:7; }
image_haproxy() { debian_service haproxy bridgeos/haproxy:2.6; }
image_registry() { debian_service registry bridgeos/registry:2.8; }

PARENT_python=base
PARENT_cloud=python
PARENT_agent=python
PARENT_postgres=base
PARENT_redis=base
PARENT_haproxy=base
PARENT_registry=base

ensure() {  # image name: its parents first, each once
    local name=$1 parent_var="PARENT_$1"
    [[ -n ${DONE[$name]:-} ]] && return
    [[ -n ${!parent_var} ]] && ensure "${!parent_var}"
    "image_$name"
    DONE[$name]=1
}

if ! docker info >/dev/null 2>&1; then
    echo "build-images: docker is not reachable; run scripts/services.sh docker" >&2
    exit 1
fi
if (($#)); then wanted=("$@"); else wanted=("${DEFAULT_IMAGES[@]}"); fi
if [[ " ${wanted[*]} " == *" stack "* ]]; then
    # Two chains that share nothing but the base (python -> cloud, agent; the Debian services),
    # built side by side: each waits mostly on downloads and unpacking, not on the other.
    ensure base
    failed=0
    bash "${BASH_SOURCE[0]}" python cloud agent & chain_python=$!
    bash "${BASH_SOURCE[0]}" postgres redis haproxy registry & chain_debian=$!
    wait "$chain_python" || failed=1
    wait "$chain_debian" || failed=1
    ((failed == 0)) || exit 1
    wanted=("${wanted[@]/stack/}")
fi
for name in "${wanted[@]}"; do
    [[ -n $name ]] || continue
    [[ " ${IMAGES[*]} " == *" $name "* ]] || { echo "build-images: unknown image $name (known: ${IMAGES[*]})" >&2; exit 2; }
    ensure "$name"
done

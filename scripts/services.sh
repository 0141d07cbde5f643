#!/usr/bin/env bash
# Make sure the real services bridgeOS runs and tests against are up.
#
#   scripts/services.sh                  # all parts: postgres redis docker swarm ros images chromium vpn prometheus node registry haproxy
#   scripts/services.sh docker ros       # only these parts (swarm and images imply docker)
#
# Idempotent: a part already up is left alone. Missing software is installed with apt
# when run as root (one batched apt-get call); otherwise the script says what is missing
# and how to get it, carries on with the other parts, and exits nonzero at the end.
# It never stops a service: only starts those that are down.
set -euo pipefail

ROOT_DIR="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
ALL_PARTS=(postgres redis docker swarm ros images chromium vpn prometheus node registry haproxy)
# Debian's prometheus scrapes `make run`'s cloud and demo agents (docker/prometheus/prometheus.yml);
# the tests start their own with a temporary config and use promtool from the same package.
# Not Prometheus's own default, 9090: that is rosbridge's, which ROS tools (roslibpy, roslibjs) assume.
PROMETHEUS_PORT="${BRIDGEOS_PROMETHEUS_PORT:-9190}"
PROMETHEUS_DIR=/var/lib/bridgeos/prometheus
PROMETHEUS_LOG=/var/log/bridgeos-prometheus.log
# The private networks' tests and benchmark: OpenVPN, nftables, ip netns (iproute2) and ping.
VPN_TOOLS=(openvpn:openvpn nft:nftables ip:iproute2 ping:iputils-ping)
# The dashboard's browser tests drive Debian's Chromium through Playwright (never Playwright's download).
CHROMIUM=/usr/bin/chromium
ROS_PACKAGES=(ros-core python3-rospy python3-rostopic python3-std-msgs python3-sensor-msgs
              python3-geometry-msgs python3-nav-msgs python3-rosservice python3-std-srvs python3-rosgraph-msgs)
DOCKERD_LOG=/var/log/bridgeos-dockerd.log
ROSCORE_LOG=/var/log/bridgeos-roscore.log
ROS_HOME_DIR=/var/lib/bridgeos/ros
ROS_PORT=11311
# The use-case Skills' nodes (bridgeos_agent.usecases) compute with numpy under the ROS python.
ROS_PACKAGES+=(python3-numpy)
export DEBIAN_FRONTEND=noninteractive NEEDRESTART_MODE=l  # never prompt, never restart services
export PATH="$PATH:/usr/sbin:/sbin"

# ROS tools are Debian python scripts (#!/usr/bin/python3); keep pyenv shims, a venv
# and its PYTHONPATH away from them.
ros_env() {
    env -u PYTHONPATH -u VIRTUAL_ENV PATH="/usr/bin:/bin:/usr/sbin:/sbin" \
        ROS_MASTER_URI="http://127.0.0.1:${ROS_PORT}" ROS_HOME="$ROS_HOME_DIR" "$@"
}

is_root() { [[ $(id -u) -eq 0 ]]; }
have() { command -v "$1" >/dev/null 2>&1; }
port_open() { (exec 3<>"/dev/tcp/127.0.0.1/$1") 2>/dev/null; }
proc_running() {  # exact process name; /proc rather than pgrep, procps may be absent
    local comm
    for comm in /proc/[0-9]*/comm; do
        [[ $(cat "$comm" 2>/dev/null) == "$1" ]] && return 0
    done
    return 1
}
now() { date +%s.%N; }
elapsed() { awk -v s="$1" -v e="$(now)" 'BEGIN { printf "%.1fs", e - s }'; }

FAILED=()
report() {  # part, start time, message
    printf '%-9s %s [%s]\n' "$1:" "$3" "$(elapsed "$2")"
}
missing() {  # part, start time, message
    report "$1" "$2" "MISSING - $3"
    FAILED+=("$1")
}

wait_for() {  # seconds, command...
    local deadline=$((SECONDS + $1)); shift
    until "$@" >/dev/null 2>&1; do
        ((SECONDS < deadline)) || return 1
        sleep 0.5
    done
}

# --- which parts -----------------------------------------------------------------
if (($#)); then REQUESTED=("$@"); else REQUESTED=("${ALL_PARTS[@]}"); fi
for part in "${REQUESTED[@]}"; do
    [[ " ${ALL_PARTS[*]} " == *" $part "* ]] || { echo "unknown part: $part (known: ${ALL_PARTS[*]})" >&2; exit 2; }
done
wants() { [[ " ${REQUESTED[*]} " == *" $1 "* ]]; }
if ! wants docker && { wants swarm || wants images; }; then REQUESTED=(docker "${REQUESTED[@]}"); fi

# --- one batched apt-get for everything missing ------------------------------------
rospy_ok() { ros_env /usr/bin/python3 -c 'import rospy, rostopic, rosservice, std_msgs.msg, std_srvs.srv, rosgraph_msgs.msg' >/dev/null 2>&1; }
APT_NEEDED=()
INSTALLED=" "
wants docker && ! have dockerd && APT_NEEDED+=(docker.io)
wants images && ! have debootstrap && APT_NEEDED+=(debootstrap)
numpy_ok() { ros_env /usr/bin/python3 -c 'import numpy' >/dev/null 2>&1; }
wants ros && { [[ -x /usr/bin/roscore ]] && rospy_ok && numpy_ok || APT_NEEDED+=("${ROS_PACKAGES[@]}"); }
wants chromium && [[ ! -x $CHROMIUM ]] && APT_NEEDED+=(chromium)
wants prometheus && { have prometheus && have promtool || APT_NEEDED+=(prometheus); }
wants node && { have node && have npm || APT_NEEDED+=(nodejs npm); }
wants registry && { have docker-registry && have skopeo || APT_NEEDED+=(docker-registry skopeo); }
wants haproxy && { have haproxy || APT_NEEDED+=(haproxy); }
if wants vpn; then
    for tool in "${VPN_TOOLS[@]}"; do have "${tool%%:*}" || APT_NEEDED+=("${tool#*:}"); done
fi
if ((${#APT_NEEDED[@]})); then
    t=$(now)
    if is_root && have apt-get; then
        apt_log=/var/log/bridgeos-apt.log
        if apt-get update >"$apt_log" 2>&1 &&
           apt-get install -y "${APT_NEEDED[@]}" >>"$apt_log" 2>&1; then
            report apt "$t" "installed ${APT_NEEDED[*]} (log $apt_log)"
            INSTALLED=" ${APT_NEEDED[*]} "
        else
            report apt "$t" "FAILED to install ${APT_NEEDED[*]}, see $apt_log:"
            tail -5 "$apt_log" | sed 's/^/    /'
        fi
    else
        report apt "$t" "cannot install (need root and apt-get): ${APT_NEEDED[*]}"
    fi
fi

# --- parts -----------------------------------------------------------------------
part_postgres() {
    local t; t=$(now); local did="already running"
    if ! port_open 5432; then
        local versions; versions=$(ls /etc/postgresql 2>/dev/null | sort -V | tail -1 || true)
        if [[ -z $versions ]]; then
            missing postgres "$t" "nothing on 127.0.0.1:5432 and PostgreSQL is not installed: sudo apt-get install postgresql"; return
        elif ! is_root; then
            missing postgres "$t" "nothing on 127.0.0.1:5432: sudo pg_ctlcluster $versions main start"; return
        fi
        pg_ctlcluster --skip-systemctl-redirect "$versions" main start
        wait_for 30 port_open 5432 || { missing postgres "$t" "started cluster $versions/main but 5432 never opened"; return; }
        did="started cluster $versions/main"
    fi
    local pg=(psql -h 127.0.0.1 -U "${PGUSER:-postgres}" -d postgres -tAq)
    if ! have psql; then
        report postgres "$t" "$did (psql missing: cannot check database test)"; return
    fi
    if [[ $("${pg[@]}" -c "SELECT 1 FROM pg_database WHERE datname = 'test'" 2>/dev/null) != 1 ]]; then
        "${pg[@]}" -c 'CREATE DATABASE test' >/dev/null || { missing postgres "$t" "$did, could not create database test"; return; }
        did+=", created database test"
    else
        did+=", database test present"
    fi
    report postgres "$t" "$did"
}

part_redis() {
    local t; t=$(now)
    if port_open 6379; then report redis "$t" "already running"; return; fi
    if ! have redis-server; then
        missing redis "$t" "nothing on 127.0.0.1:6379 and redis-server not installed: sudo apt-get install redis-server"; return
    fi
    mkdir -p /var/lib/redis /var/log/redis 2>/dev/null || true
    redis-server --daemonize yes --bind 127.0.0.1 -::1 --port 6379 --save "" --appendonly no \
        --dir /var/lib/redis --logfile /var/log/redis/ci.log >/dev/null
    if wait_for 15 port_open 6379; then
        report redis "$t" "started (log /var/log/redis/ci.log)"
    else
        missing redis "$t" "started redis-server but 6379 never opened, see /var/log/redis/ci.log"
    fi
}

docker_up() { docker info >/dev/null 2>&1; }

part_docker() {
    local t; t=$(now)
    if docker_up; then report docker "$t" "dockerd already running"; return; fi
    if ! have dockerd; then
        missing docker "$t" "dockerd not installed: sudo apt-get install docker.io (or run this script as root)"; return
    fi
    local did
    if proc_running dockerd; then
        if [[ $(docker info 2>&1 || true) == *"permission denied"* ]]; then
            missing docker "$t" "dockerd runs but $(id -un) cannot use its socket: sudo usermod -aG docker $(id -un) (then log in again), or run as root"; return
        fi
        did="dockerd was starting, now up"
    elif ! is_root; then
        missing docker "$t" "dockerd not running: sudo $0 docker (or start your docker service)"; return
    else
        # --bridge must stay default: containers on the docker0 bridge need it.
        setsid nohup dockerd --storage-driver=overlay2 >>"$DOCKERD_LOG" 2>&1 </dev/null &
        did="started dockerd (log $DOCKERD_LOG)"
        [[ $INSTALLED == *" docker.io "* ]] && did="installed docker.io, $did"
    fi
    if wait_for 60 docker_up; then
        report docker "$t" "$did"
    else
        missing docker "$t" "dockerd did not answer within 60 s, see $DOCKERD_LOG"
    fi
}

part_swarm() {
    local t; t=$(now)
    if ! docker_up; then missing swarm "$t" "needs docker: scripts/services.sh docker"; return; fi
    if [[ $(docker info --format '{{.Swarm.LocalNodeState}}' 2>/dev/null) == active ]]; then
        report swarm "$t" "already active"; return
    fi
    if docker swarm init --advertise-addr 127.0.0.1 >/dev/null; then
        report swarm "$t" "initialised single-node swarm (advertise 127.0.0.1)"
    else
        missing swarm "$t" "docker swarm init failed"
    fi
}

rostopic_ok() { ros_env timeout 10 /usr/bin/python3 /usr/bin/rostopic list >/dev/null 2>&1; }

part_ros() {
    local t; t=$(now)
    if [[ ! -x /usr/bin/roscore ]] || ! rospy_ok; then
        missing ros "$t" "roscore/rospy not installed: sudo apt-get install ${ROS_PACKAGES[*]}"; return
    fi
    local did
    if port_open "$ROS_PORT"; then
        did="roscore already running on :$ROS_PORT"
    else
        mkdir -p "$ROS_HOME_DIR" 2>/dev/null || { missing ros "$t" "cannot create $ROS_HOME_DIR (run as root)"; return; }
        ros_env setsid nohup /usr/bin/python3 /usr/bin/roscore -p "$ROS_PORT" >>"$ROSCORE_LOG" 2>&1 </dev/null &
        did="started roscore -p $ROS_PORT (log $ROSCORE_LOG)"
        [[ $INSTALLED == *" ros-core "* ]] && did="installed ROS packages, $did"
    fi
    if wait_for 30 rostopic_ok; then
        report ros "$t" "$did"
    else
        missing ros "$t" "$did, but rostopic list fails; see $ROSCORE_LOG"
    fi
}

part_images() {
    local t; t=$(now)
    if ! docker_up; then missing images "$t" "needs docker: scripts/services.sh docker"; return; fi
    if ! have debootstrap; then missing images "$t" "debootstrap not installed: sudo apt-get install debootstrap"; return; fi
    if bash "$ROOT_DIR/docker/build-images.sh"; then
        report images "$t" "bridgeos/base:bookworm and bridgeos/ros:noetic ready"
    else
        missing images "$t" "docker/build-images.sh failed (see its output above)"
    fi
}

part_chromium() {
    local t; t=$(now)
    if [[ ! -x $CHROMIUM ]]; then
        missing chromium "$t" "$CHROMIUM not installed (browser tests will skip): sudo apt-get install chromium"; return
    fi
    local did="present"
    [[ $INSTALLED == *" chromium "* ]] && did="installed"
    # Debian's wrapper script prints a shell warning before the version on some systems; keep the version line.
    report chromium "$t" "$did: $("$CHROMIUM" --version 2>/dev/null | grep -m1 -i chromium || echo "version unknown")"
}

part_vpn() {
    local t; t=$(now); local absent=()
    for tool in "${VPN_TOOLS[@]}"; do have "${tool%%:*}" || absent+=("${tool#*:}"); done
    if ((${#absent[@]})); then
        missing vpn "$t" "not installed (the VPN tests skip): sudo apt-get install ${absent[*]}"; return
    fi
    report vpn "$t" "$(openvpn --version 2>/dev/null | head -1 | cut -d' ' -f1-2), $(nft --version 2>/dev/null)"
}

part_prometheus() {
    local t; t=$(now)
    if ! have prometheus || ! have promtool; then
        missing prometheus "$t" "not installed (the observability tests need it): sudo apt-get install prometheus"; return
    fi
    local did pid
    # An earlier version of this script ran it on 9090, rosbridge's port: that one is ours to move.
    for pid in /proc/[0-9]*; do
        pid=${pid#/proc/}
        [[ $(cat "/proc/$pid/comm" 2>/dev/null) == prometheus ]] || continue
        if tr '\0' ' ' <"/proc/$pid/cmdline" 2>/dev/null | grep -q -- "--web.listen-address=127.0.0.1:9090"; then
            kill "$pid" 2>/dev/null && echo "prometheus: stopped the one this script started on :9090 (rosbridge's port)"
        fi
    done
    if port_open "$PROMETHEUS_PORT"; then
        did="already running on :$PROMETHEUS_PORT"
    else
        mkdir -p "$PROMETHEUS_DIR" 2>/dev/null || { missing prometheus "$t" "cannot create $PROMETHEUS_DIR (run as root)"; return; }
        # Debian's package would run it under systemd; here it runs like the other parts, detached.
        setsid nohup prometheus --config.file="$ROOT_DIR/docker/prometheus/prometheus.yml" \
            --storage.tsdb.path="$PROMETHEUS_DIR" --web.listen-address="127.0.0.1:$PROMETHEUS_PORT" \
            >>"$PROMETHEUS_LOG" 2>&1 </dev/null &
        did="started on 127.0.0.1:$PROMETHEUS_PORT (log $PROMETHEUS_LOG)"
        [[ $INSTALLED == *" prometheus "* ]] && did="installed prometheus, $did"
    fi
    if wait_for 30 port_open "$PROMETHEUS_PORT"; then
        report prometheus "$t" "$did, $(prometheus --version 2>&1 | head -1 | cut -d' ' -f1-3)"
    else
        missing prometheus "$t" "$did, but :$PROMETHEUS_PORT never opened; see $PROMETHEUS_LOG"
    fi
}

# The real JavaScript clients the tests drive with Node (tests/js/<client>/, each with its package-lock.json).
part_node() {
    local t; t=$(now)
    if ! have node || ! have npm; then
        missing node "$t" "node/npm not installed (the JavaScript client tests skip): sudo apt-get install nodejs npm"; return
    fi
    local did=() dir
    for dir in "$ROOT_DIR"/tests/js/*/; do
        [[ -f $dir/package-lock.json ]] || continue
        # npm ci wipes and reinstalls: only when the lock file changed since the last install.
        if [[ ! $dir/node_modules/.package-lock.json -nt $dir/package-lock.json ]]; then
            if ! (cd "$dir" && npm ci --no-audit --no-fund --loglevel=error >/dev/null 2>&1); then
                missing node "$t" "npm ci failed in ${dir#"$ROOT_DIR"/}: run it there to see why"; return
            fi
            did+=("installed ${dir#"$ROOT_DIR"/}")
        fi
    done
    ((${#did[@]})) || did=("packages up to date")
    report node "$t" "node $(node --version), ${did[*]}"
}

# Debian's CNCF Distribution registry and skopeo. With the project installed (make install), a
# registry for `make run`'s cloud starts too, as a standing service like PostgreSQL: on
# 127.0.0.1:$REGISTRY_PORT, its storage and config under the default data directory, tokens from
# the cloud `make run` serves (which then uses this registry instead of starting its own). The
# tests start their own registries on free ports.
REGISTRY_PORT="${BRIDGEOS_REGISTRY_PORT:-5000}"
REGISTRY_DIR="${BRIDGEOS_DATA_DIR:-$ROOT_DIR/.data}/registry"
REGISTRY_LOG=/var/log/bridgeos-registry.log
registry_running() {  # the registry this script started for this data directory answers
    local pid
    pid=$(cat "$REGISTRY_DIR/registry.pid" 2>/dev/null) || return 1
    [[ $(cat "/proc/$pid/comm" 2>/dev/null) == docker-registry ]] && port_open "$REGISTRY_PORT"
}
part_registry() {
    local t; t=$(now)
    if ! have docker-registry || ! have skopeo; then
        missing registry "$t" "not installed (the registry tests need them): sudo apt-get install docker-registry skopeo"; return
    fi
    local did="present"
    [[ $INSTALLED == *" docker-registry "* ]] && did="installed"
    local version
    version="docker-registry $(docker-registry --version 2>/dev/null | awk '{print $3}'), $(skopeo --version 2>/dev/null)"
    if registry_running; then
        report registry "$t" "$version; already running on 127.0.0.1:$REGISTRY_PORT (log $REGISTRY_LOG)"; return
    fi
    if port_open "$REGISTRY_PORT"; then
        report registry "$t" "$did: $version; port $REGISTRY_PORT is taken by something else, none started (set BRIDGEOS_REGISTRY_PORT)"; return
    fi
    if [[ ! -x $ROOT_DIR/.venv/bin/python ]]; then
        report registry "$t" "$did: $version; make run starts one (make install first to start it here)"; return
    fi
    mkdir -p "$REGISTRY_DIR"
    if ! (cd "$ROOT_DIR" && .venv/bin/python manage.py registry_config \
            --realm "http://127.0.0.1:${BRIDGEOS_PORT:-8000}/api/registry/token" \
            --listen "127.0.0.1:$REGISTRY_PORT" --storage "$REGISTRY_DIR/storage" --out "$REGISTRY_DIR") \
            >>"$REGISTRY_LOG" 2>&1; then
        missing registry "$t" "manage.py registry_config failed, see $REGISTRY_LOG"; return
    fi
    setsid nohup docker-registry serve "$REGISTRY_DIR/config.yml" >>"$REGISTRY_LOG" 2>&1 </dev/null &
    echo $! >"$REGISTRY_DIR/registry.pid"
    local _
    for _ in $(seq 1 100); do registry_running && break; sleep 0.1; done
    if ! registry_running; then
        missing registry "$t" "docker-registry did not start, see $REGISTRY_LOG"; return
    fi
    report registry "$t" "$did: $version; started on 127.0.0.1:$REGISTRY_PORT for make run's cloud (log $REGISTRY_LOG)"
}

# The load balancer the stack runs in its image, on the host for `benchmarks/tenk.py --balancer`,
# which starts its own in front of its daphnes: installed here, never started.
part_haproxy() {
    local t; t=$(now)
    if ! have haproxy; then
        missing haproxy "$t" "not installed (tenk.py --balancer needs it): sudo apt-get install haproxy"; return
    fi
    local did="present"
    [[ $INSTALLED == *" haproxy "* ]] && did="installed"
    report haproxy "$t" "$did: $(haproxy -v 2>/dev/null | head -1 | awk '{print $1, $2, $3}'); the benchmarks start their own"
}

for part in "${ALL_PARTS[@]}"; do
    wants "$part" || continue
    "part_$part"
done

if ((${#FAILED[@]})); then
    echo "services: missing ${FAILED[*]}" >&2
    exit 1
fi
echo "services: all up (${REQUESTED[*]})"

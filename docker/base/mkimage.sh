#!/usr/bin/env bash
# Debootstrap a minimal Debian and import it as a docker image: mkimage.sh TAG INPUTS_HASH
#
# The mirror is the one this host's apt uses (override with BRIDGEOS_DEBIAN_MIRROR), so
# the build works wherever the host can install packages.
set -euo pipefail

TAG=$1
INPUTS=$2
SUITE=${BRIDGEOS_DEBIAN_SUITE:-bookworm}
HERE="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
LOG=${BRIDGEOS_LOG_DIR:-/var/log}/bridgeos-debootstrap.log

host_mirror() {  # first plain "deb" URI serving $SUITE, in one-line or deb822 sources
    local f
    for f in /etc/apt/sources.list /etc/apt/sources.list.d/*.list; do
        [[ -r $f ]] || continue
        awk -v suite="$SUITE" '$1 == "deb" {
            i = 2; if ($i ~ /^\[/) while ($i !~ /\]$/) i++; if ($i ~ /\]$/ && $i ~ /^\[|=/) i++
            if ($(i + 1) == suite) { print $i; exit }
        }' "$f"
    done
    for f in /etc/apt/sources.list.d/*.sources; do
        [[ -r $f ]] || continue
        awk -v suite="$SUITE" 'BEGIN { RS = ""; FS = "\n" } {
            types = uris = suites = ""; enabled = 1
            for (i = 1; i <= NF; i++) {
                if ($i ~ /^#/) continue
                split($i, kv, /:[ \t]*/)
                if (kv[1] == "Types") types = " " substr($i, 8) " "
                if (kv[1] == "URIs") { uris = substr($i, 6); sub(/^[ \t]+/, "", uris) }
                if (kv[1] == "Suites") suites = " " substr($i, 8) " "
                if (kv[1] == "Enabled" && $i ~ /no/) enabled = 0
            }
            if (enabled && types ~ / deb / && suites ~ (" " suite " ")) { split(uris, u, /[ \t]+/); print u[1]; exit }
        }' "$f"
    done
}

MIRROR=${BRIDGEOS_DEBIAN_MIRROR:-$(host_mirror | head -1)}
MIRROR=${MIRROR:-http://deb.debian.org/debian}

ROOTFS=$(mktemp -d /var/tmp/bridgeos-rootfs.XXXXXX)
trap 'rm -rf --one-file-system "$ROOTFS"' EXIT

echo "    debootstrap --variant=minbase $SUITE from $MIRROR (log $LOG)"
if ! debootstrap --variant=minbase "$SUITE" "$ROOTFS" "$MIRROR" >"$LOG" 2>&1; then
    echo "debootstrap failed, last lines of $LOG:" >&2
    tail -20 "$LOG" >&2
    exit 1
fi

# Same slimming the official Debian images do: no package caches, lists or docs kept.
cp "$HERE/apt-docker-clean.conf" "$ROOTFS/etc/apt/apt.conf.d/docker-clean"
rm -rf "$ROOTFS"/var/cache/apt/*.bin "$ROOTFS"/var/cache/apt/archives/*.deb \
       "$ROOTFS"/var/lib/apt/lists/* "$ROOTFS"/var/log/*.log "$ROOTFS"/tmp/*
rm -f "$ROOTFS"/etc/hostname "$ROOTFS"/etc/resolv.conf

echo "    docker import $TAG"
tar --numeric-owner -C "$ROOTFS" -c . | docker import \
    --change "LABEL org.bridgeos.inputs=$INPUTS" \
    --change 'ENV LANG=C.UTF-8' \
    --change 'CMD ["bash"]' \
    - "$TAG" >/dev/null

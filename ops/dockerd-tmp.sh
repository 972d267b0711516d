#!/bin/sh
# A throwaway Docker engine for a machine that runs none (no systemd, a CI box, a container
# with privileges): its data, sockets and pid file under one temporary folder, removed again
# by `stop`, together with the docker0 bridge and the iptables rules the engine added.
#
#   eval "$(ops/dockerd-tmp.sh start)"     prints DOCKER_HOST=... and CUBOID_DOCKERD_DIR=...
#   ops/dockerd-tmp.sh stop "$CUBOID_DOCKERD_DIR"
#
# Needs root and Debian's docker.io and iptables packages (dockerd, containerd, runc).
# DOCKERD_ROOT (default: a new folder under ${TMPDIR:-/tmp}) holds the engine's images:
# the project's build peaks at about 24 GB there.
set -eu

tables="filter nat mangle raw"

snapshot() {  # the rules of every table, one per line, for the diff in stop
    for t in $tables; do
        iptables -t "$t" -S 2>/dev/null | sed "s/^/$t /" || true
    done
}

start() {
    command -v dockerd > /dev/null || { echo "dockerd-tmp: no dockerd (apt install docker.io)" >&2; exit 1; }
    [ "$(id -u)" = 0 ] || { echo "dockerd-tmp: dockerd needs root" >&2; exit 1; }
    dir=${DOCKERD_ROOT:-$(mktemp -d "${TMPDIR:-/tmp}/cuboid-dockerd.XXXXXX")}
    mkdir -p "$dir"
    snapshot > "$dir/iptables.before"
    cat /proc/sys/net/ipv4/ip_forward > "$dir/ip_forward.before"
    ip link show docker0 > /dev/null 2>&1 && echo keep > "$dir/docker0.before" || true
    dockerd --data-root "$dir/data" --exec-root "$dir/exec" --pidfile "$dir/dockerd.pid" \
        --host "unix://$dir/docker.sock" > "$dir/dockerd.log" 2>&1 &
    echo $! > "$dir/dockerd.pid.started"
    i=0
    until DOCKER_HOST="unix://$dir/docker.sock" docker version > /dev/null 2>&1; do
        i=$((i + 1))
        if [ "$i" -gt 60 ] || ! kill -0 "$(cat "$dir/dockerd.pid.started")" 2>/dev/null; then
            echo "dockerd-tmp: the engine did not start; its log:" >&2
            tail -20 "$dir/dockerd.log" >&2
            stop "$dir" >&2
            exit 1
        fi
        sleep 1
    done
    echo "DOCKER_HOST=unix://$dir/docker.sock; export DOCKER_HOST"
    echo "CUBOID_DOCKERD_DIR=$dir; export CUBOID_DOCKERD_DIR"
}

stop() {
    dir=$1
    [ -f "$dir/iptables.before" ] || { echo "dockerd-tmp: $dir was not made by start" >&2; exit 1; }
    if [ -f "$dir/dockerd.pid.started" ]; then
        pid=$(cat "$dir/dockerd.pid.started")
        if kill -0 "$pid" 2>/dev/null; then
            kill -TERM "$pid"
            i=0
            while kill -0 "$pid" 2>/dev/null && [ "$i" -lt 60 ]; do sleep 1; i=$((i + 1)); done
            kill -0 "$pid" 2>/dev/null && kill -KILL "$pid" || true
        fi
    fi
    # Rules the engine added (and chains it created), removed in reverse order.
    snapshot | grep -vxF -f "$dir/iptables.before" | tac | while read -r t op rest; do
        case "$op" in
            -A) eval "iptables -t $t -D $rest" || true ;;
        esac
    done
    snapshot | grep -vxF -f "$dir/iptables.before" | while read -r t op chain; do
        case "$op" in
            -N) iptables -t "$t" -X "$chain" || true ;;
        esac
    done
    # Chain policies as they were (the engine sets FORWARD to DROP when it turns forwarding on).
    grep ' -P ' "$dir/iptables.before" | while read -r t op chain policy; do
        iptables -t "$t" -P "$chain" "$policy" || true
    done
    [ -f "$dir/docker0.before" ] || ip link delete docker0 2>/dev/null || true
    cat "$dir/ip_forward.before" > /proc/sys/net/ipv4/ip_forward 2>/dev/null || true
    # The engine is down: its overlay mounts are gone with it; unmount any it left behind.
    grep -o " $dir/[^ ]*" /proc/mounts | sort -r | while read -r m; do umount -l "$m" || true; done
    rm -rf "$dir"
    echo "dockerd-tmp: stopped, $dir removed"
}

case "${1:-}" in
    start) start ;;
    stop) [ $# -eq 2 ] || { echo "usage: $0 stop DIR" >&2; exit 2; }; stop "$2" ;;
    *) echo "usage: $0 start | stop DIR" >&2; exit 2 ;;
esac

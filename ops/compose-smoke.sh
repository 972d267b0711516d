#!/bin/bash
# End-to-end check of docker-compose.yml on a real Docker engine (docs/operations.md:
# Containers; RELIABILITY.md: Compose smoke run). It
#   1. uses the engine DOCKER_HOST points at, or starts a throwaway one (ops/dockerd-tmp.sh,
#      root and Debian's docker.io package) when none answers;
#   2. uses python:3.11-slim when a registry gives it, else builds a Debian bookworm base
#      locally (mmdebstrap) and imports it;
#   3. builds the project image through compose, passing the host's pip index and its extra
#      CA certificates (/usr/local/share/ca-certificates) as build arguments, read now:
#      nothing of this machine is written into the project;
#   4. runs `up` with small settings and checks: the generator writes and turns healthy; the
#      trainer turns healthy, trains and checkpoints; `stop` ends both with exit code 0; a
#      second `up` resumes from last.pt; a generator that finishes (CUBOIDGEN_MAX_SAMPLES)
#      does not keep the trainer from starting and training; `down` leaves nothing behind;
#   5. removes, on any exit, what it started: the compose project with its volumes, a base
#      tar it made, and a throwaway engine with its data root, bridge and iptables rules.
#      Images it built on an engine it did not start stay there (the build cache):
#      `docker image rm cuboid-fit:cpu cuboid-fit:cuda cuboid-base:bookworm` removes them.
#
#   ops/compose-smoke.sh                       everything chosen as above
#   TORCH_VARIANT=cuda ops/compose-smoke.sh    choose the variant (default: cpu where
#                                              PyTorch's CPU index answers, else cuda)
#
# Settings read from the environment: TORCH_VARIANT, TORCH_INDEX, PYPI_INDEX, BASE_IMAGE,
# BUILD_CA_CERTS, BUILD_PIP_CONF (the Dockerfile's build arguments), COMPOSE (the compose
# command, e.g. "docker-compose" or "docker compose"), CUBOID_BASE_TAR (keep the mmdebstrap
# tar there and reuse it), CUBOID_SMOKE_TIMEOUT (seconds each wait may take, default 600).
set -euo pipefail

ROOT=$(cd "$(dirname "$0")/.." && pwd)
PROJECT=cuboid-smoke-$$
T0=$(date +%s)
WAIT=${CUBOID_SMOKE_TIMEOUT:-600}
LOCAL_BASE=cuboid-base:bookworm
CPU_INDEX=https://download.pytorch.org/whl/cpu
cleanup_dirs=()
own_engine=
compose_up=

say() { printf '[%4ds] %s\n' "$(($(date +%s) - T0))" "$*"; }
die() { say "FAIL: $*"; exit 1; }

compose() { $COMPOSE -p "$PROJECT" -f "$ROOT/docker-compose.yml" "$@"; }

cleanup() {
    rc=$?
    set +e
    if [ -n "$compose_up" ]; then
        if [ "$rc" != 0 ]; then
            say "logs of the failed run (last 40 lines):"
            compose logs --no-color --tail 40 2>&1 | sed 's/^/    /'
        fi
        compose down -v --remove-orphans > /dev/null 2>&1
        say "cleanup: compose project $PROJECT down, its volumes removed"
    fi
    for d in "${cleanup_dirs[@]}"; do rm -rf "$d"; done
    if [ -n "$own_engine" ]; then
        "$ROOT/ops/dockerd-tmp.sh" stop "$own_engine" | sed 's/^/    /'
        say "cleanup: throwaway engine stopped, its data root, bridge and iptables rules removed"
    fi
    if [ "$rc" = 0 ]; then say "PASS"; else say "FAIL (exit $rc)"; fi
    exit "$rc"
}
trap cleanup EXIT
trap 'exit 130' INT TERM

# --- 1. an engine and a compose ------------------------------------------------------------
if ! docker version > /dev/null 2>&1; then
    say "no Docker engine answers: starting a throwaway one (ops/dockerd-tmp.sh)"
    eval "$("$ROOT/ops/dockerd-tmp.sh" start)"
    own_engine=$CUBOID_DOCKERD_DIR
fi
if [ -z "${COMPOSE:-}" ]; then
    if docker compose version > /dev/null 2>&1; then COMPOSE="docker compose"
    elif command -v docker-compose > /dev/null; then COMPOSE=docker-compose
    else die "neither \`docker compose\` (v2) nor docker-compose (v1) is installed"; fi
fi
say "engine $(docker version -f '{{.Server.Version}}'), $($COMPOSE version | head -1), project $PROJECT"

# --- 2. a base image -----------------------------------------------------------------------
if [ -z "${BASE_IMAGE:-}" ]; then
    if docker image inspect python:3.11-slim > /dev/null 2>&1 \
            || timeout 120 docker pull -q python:3.11-slim > /dev/null 2>&1; then
        BASE_IMAGE=python:3.11-slim
    elif docker image inspect "$LOCAL_BASE" > /dev/null 2>&1; then
        BASE_IMAGE=$LOCAL_BASE
        say "no registry answers; using the local base image $LOCAL_BASE built earlier"
    else
        command -v mmdebstrap > /dev/null || die "no registry answers and no mmdebstrap (apt install mmdebstrap)"
        tar=${CUBOID_BASE_TAR:-}
        if [ -z "$tar" ]; then
            tmp=$(mktemp -d); cleanup_dirs+=("$tmp"); tar=$tmp/base.tar
        fi
        if [ ! -s "$tar" ]; then
            say "no registry answers: building a bookworm base with mmdebstrap"
            mmdebstrap --quiet --variant=minbase \
                --include=python3,python3-venv,python-is-python3,ca-certificates bookworm "$tar"
        fi
        docker import "$tar" "$LOCAL_BASE" > /dev/null
        BASE_IMAGE=$LOCAL_BASE
        say "base image $LOCAL_BASE imported ($(du -h "$tar" | cut -f1) tar)"
    fi
fi
export BASE_IMAGE

# --- 3. build arguments from the host, read now --------------------------------------------
if [ -z "${PYPI_INDEX:-}" ]; then
    for candidate in "${PIP_INDEX_URL:-}" "$(python3 -m pip config get global.index-url 2>/dev/null || true)"; do
        case "$candidate" in http://*|https://*) PYPI_INDEX=$candidate; break ;; esac
    done
fi
export PYPI_INDEX=${PYPI_INDEX:-https://pypi.org/simple}
if [ -z "${BUILD_CA_CERTS+set}" ]; then
    BUILD_CA_CERTS=$(cat /usr/local/share/ca-certificates/*.crt 2>/dev/null || true)
    say "extra CA certificates passed to the build: $(printf '%s\n' "$BUILD_CA_CERTS" | grep -c 'BEGIN CERTIFICATE' || true) (the host's /usr/local/share/ca-certificates)"
fi
export BUILD_CA_CERTS
if [ -z "${TORCH_VARIANT:-}" ]; then
    if python3 -c "import sys, urllib.request; urllib.request.urlopen(sys.argv[1] + '/torch/', timeout=20)" \
            "${TORCH_INDEX:-$CPU_INDEX}" 2> /dev/null; then
        TORCH_VARIANT=cpu
    else
        TORCH_VARIANT=cuda
        say "NOTE: ${TORCH_INDEX:-$CPU_INDEX} does not answer here, so no CPU-only torch: building" \
            "TORCH_VARIANT=cuda (PyPI's torch with its CUDA libraries; it runs on the CPU too)"
    fi
fi
export TORCH_VARIANT
IMAGE=cuboid-fit:$TORCH_VARIANT
say "build: TORCH_VARIANT=$TORCH_VARIANT BASE_IMAGE=$BASE_IMAGE PYPI_INDEX=$PYPI_INDEX"

# --- 4. build --------------------------------------------------------------------------------
t=$(date +%s)
compose build generator > "${CUBOID_SMOKE_BUILD_LOG:-/dev/null}" 2>&1 || die "compose build failed (CUBOID_SMOKE_BUILD_LOG=FILE keeps its log)"
docker run --rm "$IMAGE" python -c "import torch, sys; print('torch', torch.__version__, 'CUDA', torch.version.cuda); sys.exit((torch.version.cuda is None) != ('$TORCH_VARIANT' == 'cpu'))" \
    | sed 's/^/    /' || die "$IMAGE is not the $TORCH_VARIANT variant"
say "built $IMAGE in $(($(date +%s) - t)) s: $(docker image inspect -f '{{.Size}}' "$IMAGE" | awk '{printf "%.2f GB", $1/1e9}')"

# --- 5. up, with small settings ---------------------------------------------------------------
export CUBOIDGEN_LIMIT=400 CUBOIDGEN_WORKERS=1 CUBOIDTRAIN_BATCH_SIZE=8 CUBOIDTRAIN_CHECKPOINT_EVERY=10
export CUBOIDTRAIN_LOADER_WORKERS=1 CUBOID_HEALTH_INTERVAL=5s
unset CUBOIDGEN_MAX_SAMPLES CUBOIDTRAIN_STEPS CUBOIDTRAIN_MAX_WAIT CUBOIDTRAIN_OUT CUBOIDTRAIN_INIT

cid() { docker ps -aq --filter "label=com.docker.compose.project=$PROJECT" --filter "label=com.docker.compose.service=$1" | head -1; }
health() { docker inspect -f '{{if .State.Health}}{{.State.Health.Status}}{{end}}' "$(cid "$1")"; }
state() { docker inspect -f '{{.State.Status}} {{.State.ExitCode}}' "$(cid "$1")"; }
in_volumes() {  # a Python one-liner over the project's volumes, mounted as compose mounts them
    docker run --rm -v "${PROJECT}_spool:/spool" -v "${PROJECT}_runs:/runs" "$IMAGE" python -c "$1"
}
status_field() {  # fields of the trainer's status.json (empty when there is none yet)
    in_volumes "import json, sys
try: s = json.load(open('/runs/p1/status.json'))
except OSError: sys.exit()
c = s.get('last_checkpoint') or {}
print(s['state'].replace(' ', '_'), s['step'], c.get('step', 0), int(s['started']))"
}
until_() {  # until_ WHAT COMMAND...: poll every 2 s, at most $WAIT s
    what=$1; shift
    local t=$(date +%s)
    until "$@"; do
        [ $(($(date +%s) - t)) -lt "$WAIT" ] || die "waited $WAIT s for: $what"
        sleep 2
    done
    say "ok: $what ($(($(date +%s) - t)) s)"
}
is_healthy() { [ "$(health "$1")" = healthy ]; }
checkpoint_at_least() { read -r _ _ ckpt _ <<< "$(status_field)"; [ "${ckpt:-0}" -ge "$1" ]; }
exited_zero() { [ "$(state "$1")" = "exited 0" ]; }
samples() {  # published samples in the spool (shared.spool's names: *.cub, no leading dot)
    in_volumes "import os; print(sum(n.endswith('.cub') and not n.startswith('.') for n in os.listdir('/spool')))" 2> /dev/null || echo 0
}
has_samples() { [ "$(samples)" -gt 0 ]; }
stop_cleanly() {
    local t=$(date +%s)
    compose stop > /dev/null 2>&1 || die "compose stop failed"
    for s in generator trainer; do
        [ "$(state $s)" = "exited 0" ] || die "$s after stop: $(state $s), expected exited 0"
    done
    say "ok: stop: both exited with code 0 ($(($(date +%s) - t)) s)"
}

say "up #1: a generator without end, a trainer without --steps"
t=$(date +%s)
compose_up=1
compose up -d --no-build 2>&1 | sed 's/^/    /'
say "up returned in $(($(date +%s) - t)) s"
until_ "the generator writes samples" has_samples
until_ "the generator's healthcheck passes" is_healthy generator
until_ "the trainer's healthcheck passes" is_healthy trainer
until_ "the trainer checkpoints (step 20)" checkpoint_at_least 20
stop_cleanly
read -r st step1 ckpt1 started1 <<< "$(status_field)"
say "after stop: trainer $st at step $step1, last.pt at step $ckpt1, $(samples) samples in the spool"
[ "$st" = stopped ] && [ "$ckpt1" = "$step1" ] || die "expected a stopped trainer whose last.pt holds its last step"

say "up #2: the trainer must resume from last.pt (step $ckpt1)"
compose up -d --no-build 2>&1 | sed 's/^/    /'
t=$(date +%s); min_step=
resumed() {
    read -r st step ckpt started <<< "$(status_field)"
    if [ "${started:-0}" -gt "$started1" ]; then  # the new trainer's status
        [ -z "$min_step" ] || [ "$step" -lt "$min_step" ] && min_step=$step
        [ "$ckpt" -ge $((ckpt1 + 10)) ]
    else
        return 1
    fi
}
until_ "the second trainer checkpoints 10 steps past step $ckpt1" resumed
[ "$min_step" -ge "$ckpt1" ] || die "the second trainer was seen at step $min_step < $ckpt1: it started afresh"
say "ok: resumed: the second trainer's first status showed step $min_step (>= $ckpt1), now checkpointed at $ckpt"
until_ "the trainer's healthcheck passes again" is_healthy trainer
stop_cleanly
t=$(date +%s)
compose down 2>&1 | sed 's/^/    /'
[ -z "$(docker ps -aq --filter "label=com.docker.compose.project=$PROJECT")" ] || die "containers left after down"
say "ok: down: no container left ($(($(date +%s) - t)) s)"
compose down -v > /dev/null 2>&1

say "up #3: a generator that stops after 40 samples (CUBOIDGEN_MAX_SAMPLES), a trainer with --steps 15"
export CUBOIDGEN_MAX_SAMPLES=40 CUBOIDTRAIN_STEPS=15
t=$(date +%s)
compose up -d --no-build 2>&1 | sed 's/^/    /' || die "up failed"
say "up returned in $(($(date +%s) - t)) s"
until_ "the generator finishes (exit code 0)" exited_zero generator
say "    generator: $(state generator) after $(samples) samples; Docker's health for it: $(health generator)" \
    "(Docker marks any stopped container unhealthy; the exit code tells)"
until_ "the trainer trains its 15 steps and exits 0" exited_zero trainer
read -r st step ckpt _ <<< "$(status_field)"
[ "$st" = done ] && [ "$step" = 15 ] && [ "$ckpt" = 15 ] || die "trainer status: $st at step $step, checkpoint $ckpt"
say "ok: trainer $st at step $step, last.pt at step $ckpt"
t=$(date +%s)
compose down -v 2>&1 | sed 's/^/    /'
left=$(docker ps -aq --filter "label=com.docker.compose.project=$PROJECT"; docker volume ls -q --filter "label=com.docker.compose.project=$PROJECT"; docker network ls -q --filter "label=com.docker.compose.project=$PROJECT")
[ -z "$left" ] || die "left after down -v: $left"
compose_up=
say "ok: down -v: no container, volume or network left ($(($(date +%s) - t)) s)"

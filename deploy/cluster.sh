#!/usr/bin/env bash
# The fitting cluster as containers, on a private Docker engine (its own socket, data root and
# pid file), without any registry.
#
#   deploy/cluster.sh demo    `make cluster`: the demo sequence on server + 4 clients, the summary,
#                             then single process vs distributed. Engine state (images) is kept in
#                             build/cluster between runs; the engine is stopped at the end.
#   deploy/cluster.sh test    `make cluster-test`: the same from nothing in build/cluster-test,
#                             poses checked against a single-process run to 1e-9, then a client
#                             container killed mid-run (every frame must still come out, same
#                             poses); everything torn down at the end, also after a failure.
#   deploy/cluster.sh batch-test  `make batch-cluster-test`: from nothing, a project of 3 takes (one
#                             broken) by `mocap batch` on a Dask scheduler + 2 worker containers
#                             (deploy/docker-compose.dask.yml), checked against `mocap run` of each
#                             take; everything torn down at the end
#   deploy/cluster.sh down    stop what an interrupted run left (compose, engine, bridges)
#
# Steps: apt-get install docker.io docker-compose debootstrap when missing (root); dockerd on a
# socket under /tmp/mocap-docker.*; deploy/base-image.sh (debootstrap + docker import) as BASE;
# deploy/Dockerfile built from a staged context with the host's wheels and extra CAs.
# Settings (environment): CLUSTER_CLIENTS (4), CLUSTER_FRAMES (30), CLUSTER_NETWORK (host:
# deploy/docker-compose.host.yml, traffic on loopback only; bridge: deploy/docker-compose.yml on
# the project's own network), CLUSTER_STATE (state folder), CLUSTER_COMPOSE (docker-compose, v1
# from Debian; or a compose v2 binary), PY (python with the project installed).
set -euo pipefail

ROOT=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
cd "$ROOT"
PY=${PY:-$ROOT/.venv/bin/python}
CLIENTS=${CLUSTER_CLIENTS:-4}
FRAMES=${CLUSTER_FRAMES:-30}
NETWORK=${CLUSTER_NETWORK:-host}
IMAGE=silhouette-mocap:latest
BASE_IMAGE=mocap-base:bookworm
PROJECT=mocapcluster
IMAGE_UID=10001                 # the image's user (deploy/Dockerfile)
IMAGE_PYTHON=3.11               # Debian bookworm's python3, and python:3.11-slim's
ENGINE_START_TIMEOUT=60         # seconds
ENGINE_STOP_TIMEOUT=30          # seconds before SIGKILL
RUN_TIMEOUT=600                 # seconds for one cluster run
FIRST_FRAMES_BEFORE_KILL=2      # frames written before a client is killed
STOP_LIMIT=10                   # seconds: SIGTERM must stop a container within this
SIGTERM_SETTLE=4                # seconds a container runs before it is stopped

case $NETWORK in
    host) COMPOSE_FILE=deploy/docker-compose.host.yml ;;
    bridge) COMPOSE_FILE=deploy/docker-compose.yml ;;
    *) echo "cluster: CLUSTER_NETWORK must be host or bridge, not $NETWORK" >&2; exit 2 ;;
esac

say() { echo "cluster: $*"; }
die() { echo "cluster: error: $*" >&2; exit 1; }

STEP_START=$SECONDS
TIMES=()
step() {  # step NAME: time the previous step, announce the next
    [ -z "${STEP_NAME:-}" ] || TIMES+=("$(printf '%-28s %4d s' "$STEP_NAME" $((SECONDS - STEP_START)))")
    STEP_NAME=$1
    STEP_START=$SECONDS
    [ -z "$1" ] || say "== $1"
}

# ------------------------------------------------------------------------- tools and engine
install_tools() {
    local missing=()
    command -v dockerd >/dev/null && [ -x /usr/bin/docker ] || missing+=(docker.io)
    command -v "$COMPOSE_BIN" >/dev/null || missing+=(docker-compose)
    command -v debootstrap >/dev/null || missing+=(debootstrap)
    [ ${#missing[@]} -eq 0 ] && return 0
    [ "$(id -u)" = 0 ] || die "needs root to install ${missing[*]} (apt-get)"
    say "apt-get install ${missing[*]}"
    apt-get update -qq >"$STATE/apt.log" 2>&1 || { tail -n 20 "$STATE/apt.log" >&2; die "apt-get update failed"; }
    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "${missing[@]}" >>"$STATE/apt.log" 2>&1 \
        || { tail -n 20 "$STATE/apt.log" >&2; die "apt-get install failed"; }
}

# the engine's client, matched to it (another docker CLI may come first on PATH)
DOCKER_BIN=/usr/bin/docker
dk() { "$DOCKER_BIN" "$@"; }
COMPOSE_BIN=${CLUSTER_COMPOSE:-docker-compose}   # or a compose v2 binary
compose() { $COMPOSE_BIN --ansi never -p "$PROJECT" -f "$COMPOSE_FILE" "$@"; }

engine_start() {
    [ "$(id -u)" = 0 ] || die "the private Docker engine needs root"
    local run
    # unix socket paths are limited to 108 bytes: socket and exec root in a short /tmp folder
    run=$(mktemp -d /tmp/mocap-docker.XXXXXX)
    echo "$run" >"$STATE/engine.run"
    ip -o link show 2>/dev/null | awk -F': ' '{print $2}' | cut -d@ -f1 >"$STATE/links.before" || true
    # no default bridge, no iptables or ip_forward changes: the host's network is left as it is
    dockerd --host "unix://$run/docker.sock" --data-root "$STATE/docker" --exec-root "$run/exec" \
        --pidfile "$run/docker.pid" --bridge=none --iptables=false --ip-forward=false --ip-masq=false \
        >"$STATE/dockerd.log" 2>&1 &
    export DOCKER_HOST="unix://$run/docker.sock"
    local waited=0
    until dk version >/dev/null 2>&1; do
        if ! kill -0 $! 2>/dev/null || [ $waited -ge $ENGINE_START_TIMEOUT ]; then
            tail -n 20 "$STATE/dockerd.log" >&2
            die "dockerd did not start (log: $STATE/dockerd.log)"
        fi
        sleep 1
        waited=$((waited + 1))
    done
    say "engine $(dk version --format '{{.Server.Version}}') pid $(cat "$run/docker.pid") on $DOCKER_HOST"
}

engine_env() {  # point docker at a running private engine, if there is one
    [ -f "$STATE/engine.run" ] || return 1
    export DOCKER_HOST="unix://$(cat "$STATE/engine.run")/docker.sock"
}

# stop the engine by its pid, then whatever it left: container shims, mounts, bridges
engine_stop() {
    [ -f "$STATE/engine.run" ] || return 0
    local run pid p m waited=0
    run=$(cat "$STATE/engine.run")
    export DOCKER_HOST="unix://$run/docker.sock"
    dk network ls --filter driver=bridge --no-trunc -q 2>/dev/null | cut -c1-12 | sed 's/^/br-/' >"$STATE/bridges" || true
    pid=$(cat "$run/docker.pid" 2>/dev/null || true)
    if [ -n "$pid" ] && grep -qF -- "$run" "/proc/$pid/cmdline" 2>/dev/null; then
        kill -TERM "$pid" 2>/dev/null || true
        while kill -0 "$pid" 2>/dev/null && [ $waited -lt $ENGINE_STOP_TIMEOUT ]; do sleep 1; waited=$((waited + 1)); done
        if kill -0 "$pid" 2>/dev/null; then
            say "dockerd $pid ignored SIGTERM; killing it"
            kill -KILL "$pid" 2>/dev/null || true
        fi
        say "engine $pid stopped"
    fi
    # containerd and shims of a hard-killed engine carry our exec root in their command line
    for p in $(pgrep -f -- "$run/" 2>/dev/null || true); do
        if [ "$p" != $$ ] && kill -KILL "$p" 2>/dev/null; then say "killed leftover engine process $p"; fi
    done
    for m in $(awk -v a="$run/" -v b="$STATE/docker/" 'index($2, a) == 1 || index($2, b) == 1 {print $2}' /proc/mounts | sort -r); do
        umount -l "$m" 2>/dev/null || true
    done
    for p in docker0 $(cat "$STATE/bridges" 2>/dev/null); do
        if ip link show "$p" >/dev/null 2>&1 && ! grep -qx -- "$p" "$STATE/links.before" 2>/dev/null; then
            if ip link delete "$p"; then say "removed bridge $p"; fi
        fi
    done
    echo "$run" >"$STATE/engine.last"
    rm -rf "$run" "$STATE/engine.run"
}

# ------------------------------------------------------------------------------ images
pip_index_setting() {  # ENV_NAME KEY: the host's pip setting, when it is a network index
    local v=${!1:-}
    [ -n "$v" ] || v=$("$PY" -m pip config get "global.$2" 2>/dev/null || true)
    [ -n "$v" ] || v=$("$PY" -m pip config get "install.$2" 2>/dev/null || true)
    # file:// mirrors are not reachable from the build; the prefetched wheels stand for them
    printf '%s\n' $v | grep -E '^https?://' | head -n 1 || true
}

stage_context() {  # a small build context: the package sources, the host's CAs and wheels
    local ctx=$STATE/context f
    rm -rf "$ctx"
    mkdir -p "$ctx/deploy/extra/ca" "$ctx/deploy/extra/wheels"
    if git rev-parse --is-inside-work-tree >/dev/null 2>&1; then
        git ls-files -z -co --exclude-standard -- pyproject.toml README.md common server client deploy \
            | while IFS= read -r -d '' f; do [ -f "$f" ] && printf '%s\0' "$f"; done \
            | tar --null -T - -cf - | tar -xf - -C "$ctx"
    else
        tar --exclude=__pycache__ --exclude='deploy/data' --exclude='deploy/extra/*/*' \
            -cf - pyproject.toml README.md common server client deploy | tar -xf - -C "$ctx"
    fi
    # a TLS-intercepting proxy's authority must be trusted in the image too, or pip fails
    find /usr/local/share/ca-certificates -name '*.crt' -type f -exec cp {} "$ctx/deploy/extra/ca/" \; 2>/dev/null || true
    # the dependencies as wheels, the host's versions, through the host's pip configuration
    # (mirrors, certificates): the image then installs offline
    "$PY" -m pip freeze --exclude-editable >"$STATE/constraints.txt"
    "$PY" - >"$STATE/requirements.txt" <<'EOF'
try:
    import tomllib
except ImportError:
    import tomli as tomllib
project = tomllib.load(open("pyproject.toml", "rb"))
print("\n".join(project["build-system"]["requires"] + project["project"]["dependencies"] + ["wheel"]))
EOF
    local target=()
    if [ "$("$PY" -c 'import sys; print("%d.%d" % sys.version_info[:2])')" != "$IMAGE_PYTHON" ]; then
        target=(--python-version "$IMAGE_PYTHON" --implementation cp --abi "cp${IMAGE_PYTHON/./}"
                --platform "manylinux_2_36_$(uname -m)")
    fi
    if ! "$PY" -m pip download --quiet --only-binary=:all: --dest "$ctx/deploy/extra/wheels" "${target[@]}" \
            -r "$STATE/requirements.txt" -c "$STATE/constraints.txt" >"$STATE/pip-download.log" 2>&1; then
        tail -n 5 "$STATE/pip-download.log" >&2
        say "warning: no wheels prefetched; the image build installs from the package index"
        rm -f "$ctx"/deploy/extra/wheels/*.whl
    fi
    say "context: $(find "$ctx/deploy/extra/wheels" -name '*.whl' | wc -l) wheels, $(find "$ctx/deploy/extra/ca" -name '*.crt' | wc -l) extra CAs, $(du -sh "$ctx" | cut -f1)"
}

build_images() {
    DOCKER=$DOCKER_BIN WORKDIR= deploy/base-image.sh "$BASE_IMAGE"
    stage_context
    local args=(--build-arg "BASE=$BASE_IMAGE")
    local v
    v=$(pip_index_setting PIP_INDEX_URL index-url); [ -z "$v" ] || args+=(--build-arg "MOCAP_PIP_INDEX_URL=$v")
    v=$(pip_index_setting PIP_EXTRA_INDEX_URL extra-index-url); [ -z "$v" ] || args+=(--build-arg "MOCAP_PIP_EXTRA_INDEX_URL=$v")
    v=$(pip_index_setting PIP_TRUSTED_HOST trusted-host); [ -z "$v" ] || args+=(--build-arg "MOCAP_PIP_TRUSTED_HOST=$v")
    say "building $IMAGE (log: $STATE/build.log)"
    DOCKER_BUILDKIT=0 dk build --network host "${args[@]}" -f "$STATE/context/deploy/Dockerfile" \
        -t "$IMAGE" "$STATE/context" >"$STATE/build.log" 2>&1 || { tail -n 30 "$STATE/build.log" >&2; die "image build failed"; }
    # the layers of earlier builds would pile up in a kept data root; the context has done its job
    dk image prune -f >/dev/null
    rm -rf "$STATE/context"
    say "$IMAGE: $(dk image inspect "$IMAGE" --format '{{.Size}}' | awk '{printf "%.0f MB", $1 / 1e6}')"
}

# -------------------------------------------------------------------------------- runs
mocap_once() {  # one mocap command in a container without network, on the data folder
    dk run --rm --init --network none --user "$IMAGE_UID:$IMAGE_UID" -v "$DATA:/data" "$IMAGE" "$@"
}

free_port() {
    "$PY" -c 'import socket; s = socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])'
}

compose_env() {  # RESULT: variables the compose files read
    export MOCAP_IMAGE=$IMAGE MOCAP_DATA=$DATA MOCAP_UID=$IMAGE_UID MOCAP_GID=$IMAGE_UID
    export MOCAP_SEQUENCE=sequence MOCAP_RESULT=$1 MOCAP_MIN_CLIENTS=$CLIENTS
    local port
    port=$(free_port)
    export MOCAP_PORT=$port MOCAP_PUBLISH=127.0.0.1:$port
}

prepare_data() {
    mkdir -p "$DATA"
    rm -rf "${DATA:?}"/*
    chown "$IMAGE_UID:$IMAGE_UID" "$DATA"
    say "demo sequence: $FRAMES frames of the bundled CMU walk, 8 cameras, Cheung noise"
    mocap_once synth --out /data/sequence --frames "$FRAMES" --noise cheung --seed 0 --quiet
}

single_run() {
    say "single process: mocap fit (log: $STATE/single.log)"
    mocap_once fit /data/sequence --out /data/single --quiet >"$STATE/single.log" 2>&1 \
        || { tail -n 20 "$STATE/single.log" >&2; die "single-process fit failed"; }
}

server_log_tail() {  # LOG: the server's last lines from a compose log (v1: server_1, v2: server-1)
    grep -E '^server[-_][0-9]+ ' "$1" | tail -n 30 >&2 || tail -n 30 "$1" >&2
}

cluster_run() {  # server + CLIENTS clients until the server has written every frame
    compose_env cluster
    say "cluster: server + $CLIENTS clients, $COMPOSE_FILE (log: $STATE/cluster.log)"
    # --abort-on-container-exit: the server writes its results before it releases the clients
    timeout $RUN_TIMEOUT $COMPOSE_BIN --ansi never -p "$PROJECT" -f "$COMPOSE_FILE" up --no-build \
        --scale client="$CLIENTS" --abort-on-container-exit >"$STATE/cluster.log" 2>&1 || true
    compose down --remove-orphans --timeout 10 >>"$STATE/cluster.log" 2>&1 || true
    [ -f "$DATA/cluster/summary.json" ] || { server_log_tail "$STATE/cluster.log"; die "the cluster run wrote no summary"; }
    echo
    "$PY" deploy/compare.py "$DATA/single" "$DATA/cluster" --frames "$FRAMES" --title "cluster run (docker-compose)"
    echo
}

kill_run() {  # a client container killed mid-run: every frame still comes out, same poses
    compose_env killed
    say "fault test: server + $CLIENTS clients, one client container killed after $FIRST_FRAMES_BEFORE_KILL frames (log: $STATE/kill.log)"
    compose up -d --no-build --scale client="$CLIENTS" >"$STATE/kill.log" 2>&1 \
        || { cat "$STATE/kill.log" >&2; die "compose up failed"; }
    local server victim code started=$SECONDS
    server=$(compose ps -q server)
    until [ "$(cat "$DATA/killed/poses.jsonl" 2>/dev/null | wc -l)" -ge $FIRST_FRAMES_BEFORE_KILL ]; do
        [ "$(dk inspect -f '{{.State.Running}}' "$server")" = true ] || die "the server stopped before the kill"
        [ $((SECONDS - started)) -lt $RUN_TIMEOUT ] || die "no frame after $RUN_TIMEOUT s"
        sleep 0.5
    done
    victim=$(compose ps -q client | sed -n 1p)
    dk kill "$victim" >/dev/null
    say "killed client container ${victim:0:12} after $(wc -l <"$DATA/killed/poses.jsonl") frames"
    code=$(timeout $RUN_TIMEOUT "$DOCKER_BIN" wait "$server" || echo timeout)
    compose logs --no-color >>"$STATE/kill.log" 2>&1 || true
    compose down --remove-orphans --timeout 10 >>"$STATE/kill.log" 2>&1 || true
    [ "$code" = 0 ] || { server_log_tail "$STATE/kill.log"; die "the server exited with $code after the kill"; }
    echo
    "$PY" deploy/compare.py "$DATA/single" "$DATA/killed" --frames "$FRAMES" --expect-lost-client \
        --title "cluster run with a killed client"
    echo
}

sigterm_run() {  # docker stop (SIGTERM) ends a waiting server and a reconnecting client in time
    local role cid took code
    for role in server client; do
        # plain docker run, no --init: mocap is PID 1 and must handle SIGTERM itself
        if [ $role = server ]; then
            cid=$(dk run -d --network none --user "$IMAGE_UID:$IMAGE_UID" -v "$DATA:/data" "$IMAGE" \
                server /data/sequence --out /data/sigterm --bind tcp://127.0.0.1:5555 --min-clients 1)
        else
            cid=$(dk run -d --network none -e MOCAP_SERVER=tcp://127.0.0.1:5555 "$IMAGE" client)
        fi
        sleep "$SIGTERM_SETTLE"
        took=$SECONDS
        dk stop --time "$STOP_LIMIT" "$cid" >/dev/null
        took=$((SECONDS - took))
        code=$(dk inspect -f '{{.State.ExitCode}}' "$cid")
        dk logs "$cid" >>"$STATE/sigterm.log" 2>&1 || true
        dk rm "$cid" >/dev/null
        say "$role: SIGTERM -> exit $code in ${took} s"
        # 137: SIGKILL after the grace period, i.e. SIGTERM was ignored
        [ "$code" != 137 ] && [ "$took" -lt "$STOP_LIMIT" ] || die "$role did not stop on SIGTERM within $STOP_LIMIT s"
    done
}

# ------------------------------------------------------------------------ batch on Dask
BATCH_COMPOSE=deploy/docker-compose.dask.yml
BATCH_TAKES=3                   # takes of the batch project; the last one is broken
BATCH_FRAMES=6                  # frames per take
BATCH_WORKERS=2
batch_compose() { $COMPOSE_BIN --ansi never -p mocapbatch -f "$BATCH_COMPOSE" "$@"; }

prepare_batch_data() {  # DATA/project: takes, the last without one silhouette; DATA/alone: each take by mocap run
    mkdir -p "$DATA"
    rm -rf "${DATA:?}"/*
    chown "$IMAGE_UID:$IMAGE_UID" "$DATA"
    say "batch project: $BATCH_TAKES takes of $BATCH_FRAMES frames, the last one broken"
    local i
    for i in $(seq 1 $BATCH_TAKES); do
        mocap_once synth --out "/data/project/take$i" --frames $BATCH_FRAMES --cameras 4 --size 160x120 \
            --start $((1 + 40 * i)) --quiet
    done
    printf '[fit]\nrefine_passes = 0\n\n[report]\ngif = false\n' >"$DATA/project/Config.toml"
    rm "$DATA/project/take$BATCH_TAKES/silhouettes/cam2/000001.png"
    cp -a "$DATA/project" "$DATA/alone"
    chown -R "$IMAGE_UID:$IMAGE_UID" "$DATA"
    for i in $(seq 1 $((BATCH_TAKES - 1))); do mocap_once run "/data/alone/take$i" >/dev/null; done
}

batch_run() {  # the project on a scheduler + BATCH_WORKERS worker containers; checked against DATA/alone
    export MOCAP_IMAGE=$IMAGE MOCAP_DATA=$DATA MOCAP_UID=$IMAGE_UID MOCAP_GID=$IMAGE_UID
    DASK_PORT=$(free_port)
    export DASK_PORT
    say "dask: scheduler + $BATCH_WORKERS workers, $BATCH_COMPOSE (log: $STATE/batch.log)"
    batch_compose up -d --no-build --scale worker=$BATCH_WORKERS >"$STATE/batch.log" 2>&1 \
        || { cat "$STATE/batch.log" >&2; die "compose up failed"; }
    local code=0
    timeout $RUN_TIMEOUT "$DOCKER_BIN" run --rm --network host --user "$IMAGE_UID:$IMAGE_UID" -v "$DATA:/data" \
        "$IMAGE" batch /data/project --scheduler "tcp://127.0.0.1:$DASK_PORT" >>"$STATE/batch.log" 2>&1 || code=$?
    batch_compose logs --no-color >>"$STATE/batch.log" 2>&1 || true
    batch_compose down --remove-orphans --timeout 10 >>"$STATE/batch.log" 2>&1 || true
    # exit 1: a take failed, as the broken one must
    [ "$code" = 1 ] || { tail -n 30 "$STATE/batch.log" >&2; die "mocap batch exited with $code (expected 1)"; }
    "$PY" - "$DATA" $BATCH_TAKES <<'EOF_CHECK' || die "the batch's results differ from mocap run's"
import json, sys
from pathlib import Path
data, n = Path(sys.argv[1]), int(sys.argv[2])
takes = {t["name"]: t for t in json.loads((data / "project" / "batch.json").read_text())["takes"]}
def poses(root):
    return [json.loads(line)["params"] for line in (root / "result" / "poses.jsonl").read_text().splitlines()]
for i in range(1, n):
    name = f"take{i}"
    assert takes[name]["status"] == "done", takes[name]
    assert poses(data / "project" / name) == poses(data / "alone" / name), f"{name}: poses differ"
    print(f"cluster: {name}: done, {len(poses(data / 'project' / name))} frames, poses equal to mocap run's")
broken = takes[f"take{n}"]
assert broken["status"] == "failed" and "cam2" in broken["error"], broken
print(f"cluster: take{n}: failed as it must: {broken['error']}")
EOF_CHECK
}

# ---------------------------------------------------------------------------- teardown
teardown() {
    local status=$?
    set +e
    trap - EXIT INT TERM
    step ""
    if engine_env; then
        compose down --remove-orphans --timeout 10 >/dev/null 2>&1
        engine_stop
    fi
    if [ "${KEEP_ENGINE_DATA:-1}" = 0 ]; then
        rm -rf --one-file-system "$STATE/docker" "$STATE/context"
    fi
    leftovers
    [ ${#TIMES[@]} -eq 0 ] || { say "durations:"; printf '  %s\n' "${TIMES[@]}"; }
    say "total $((SECONDS - START)) s, $([ $status = 0 ] && echo passed || echo "FAILED ($status)")"
    exit $status
}

leftovers() {  # processes, mounts or bridges of our engine still there?
    local bad=0 p
    if pgrep -f -- "--data-root $STATE/docker" >/dev/null 2>&1; then say "LEFT: an engine process"; bad=1; fi
    if grep -qF -- "$STATE/docker/" /proc/mounts; then say "LEFT: mounts under $STATE/docker"; bad=1; fi
    p=$(cat "$STATE/engine.last" 2>/dev/null || true)
    if [ -n "$p" ] && { [ -e "$p" ] || grep -qF -- "$p/" /proc/mounts; }; then say "LEFT: $p"; bad=1; fi
    for p in docker0 $(cat "$STATE/bridges" 2>/dev/null); do
        if ip link show "$p" >/dev/null 2>&1 && ! grep -qx -- "$p" "$STATE/links.before" 2>/dev/null; then
            say "LEFT: bridge $p"; bad=1
        fi
    done
    [ $bad = 1 ] || say "clean: no engine process, container, mount or bridge left"
    return $bad
}

start_session() {  # STATE_DIR FRESH(0/1)
    STATE=$1
    DATA=$STATE/data
    START=$SECONDS
    if [ -f "$STATE/engine.run" ]; then say "stopping the engine a previous run left"; engine_stop; fi
    if [ "$2" = 1 ]; then rm -rf --one-file-system "$STATE"; fi
    mkdir -p "$STATE"
    trap teardown EXIT
    trap 'exit 130' INT
    trap 'exit 143' TERM
}

# -------------------------------------------------------------------------------- main
[ -x "$PY" ] || die "no python at $PY (make venv)"
case ${1:-} in
    demo)
        start_session "${CLUSTER_STATE:-$ROOT/build/cluster}" 0
        step "install tools"; install_tools
        step "start engine"; engine_start
        step "build images"; build_images
        step "synthesise sequence"; prepare_data
        step "single-process fit"; single_run
        step "cluster fit"; cluster_run
        ;;
    test)
        start_session "${CLUSTER_STATE:-$ROOT/build/cluster-test}" 1
        KEEP_ENGINE_DATA=0
        step "install tools"; install_tools
        step "start engine"; engine_start
        step "build images"; build_images
        step "synthesise sequence"; prepare_data
        step "single-process fit"; single_run
        step "cluster fit + compare"; cluster_run
        step "client killed mid-run"; kill_run
        step "SIGTERM"; sigterm_run
        ;;
    batch-test)
        start_session "${CLUSTER_STATE:-$ROOT/build/batch-cluster-test}" 1
        KEEP_ENGINE_DATA=0
        step "install tools"; install_tools
        step "start engine"; engine_start
        step "build images"; build_images
        step "batch project"; prepare_batch_data
        step "mocap batch on dask"; batch_run
        ;;
    down)
        for STATE in ${CLUSTER_STATE:-$ROOT/build/cluster $ROOT/build/cluster-test $ROOT/build/batch-cluster-test}; do
            if engine_env; then
                compose down --remove-orphans --timeout 10 || true
                batch_compose down --remove-orphans --timeout 10 || true
                engine_stop
            fi
            [ ! -d "$STATE" ] || leftovers || true
        done
        ;;
    *)
        sed -n '2,/^set -euo/p' "$0" | sed '$d; s/^# \{0,1\}//'
        exit 2
        ;;
esac

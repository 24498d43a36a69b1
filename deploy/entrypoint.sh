#!/bin/sh
# Container entry point: `mocap ARGS`, exec'd so that mocap itself receives the signals.
# `client`: the server address from MOCAP_SERVER (tcp://HOST:PORT) unless --connect is given,
# and a unique name unless --id is given (the default HOST-PID repeats across containers: each
# has its own PID namespace, and all share one host name under network_mode: host).
set -eu
if [ "${1:-}" = client ]; then
    shift
    connect="" name=""
    for arg in "$@"; do
        case $arg in
            --connect|--connect=*) connect=given ;;
            --id|--id=*) name=given ;;
        esac
    done
    if [ -z "$connect" ] && [ -n "${MOCAP_SERVER:-}" ]; then
        set -- --connect "$MOCAP_SERVER" "$@"
    fi
    if [ -z "$name" ]; then
        set -- --id "${MOCAP_CLIENT_ID:-$(cat /proc/sys/kernel/hostname)-$(od -An -N3 -tx1 /dev/urandom | tr -d ' \n')}" "$@"
    fi
    set -- client "$@"
fi
exec /opt/mocap/bin/mocap "$@"

#!/usr/bin/env bash
# Build a Debian base image without any registry: debootstrap a minimal root file system from
# the host's apt mirror and `docker import` it. Pass the result to the Dockerfile as BASE:
#
#   deploy/base-image.sh [TAG]          (default mocap-base:bookworm; needs root and debootstrap)
#   docker build --build-arg BASE=mocap-base:bookworm -f deploy/Dockerfile ...
#
# Environment: MIRROR (default: the first `URIs:` of /etc/apt/sources.list.d/debian.sources,
# else http://deb.debian.org/debian), SUITE (bookworm), WORKDIR (where the root file system is
# made, default a fresh directory under /tmp; removed afterwards), FORCE=1 (rebuild an existing
# TAG), BASE_PACKAGES (added to minbase; by default Python and headless OpenGL, so that the
# Dockerfile needs no apt run; set it empty for a bare minbase and the Dockerfile installs them).
set -euo pipefail

TAG=${1:-mocap-base:bookworm}
SUITE=${SUITE:-bookworm}
BASE_PACKAGES=${BASE_PACKAGES-python3 python3-venv ca-certificates libegl1 libgl1 libgl1-mesa-dri}
DOCKER=${DOCKER:-docker}

say() { echo "base-image: $*" >&2; }

host_mirror() {
    local uri
    uri=$(awk '/^URIs:/ {print $2; exit}' /etc/apt/sources.list.d/debian.sources 2>/dev/null || true)
    [ -n "$uri" ] || uri=$(awk '$1 == "deb" && $2 !~ /^\[/ {print $2; exit}' /etc/apt/sources.list 2>/dev/null || true)
    echo "${uri:-http://deb.debian.org/debian}"
}
MIRROR=${MIRROR:-$(host_mirror)}

if [ "${FORCE:-0}" != 1 ] && $DOCKER image inspect "$TAG" >/dev/null 2>&1; then
    say "$TAG exists (FORCE=1 rebuilds it)"
    exit 0
fi
[ "$(id -u)" = 0 ] || { say "debootstrap needs root"; exit 1; }
command -v debootstrap >/dev/null || { say "debootstrap missing: apt-get install -y debootstrap"; exit 1; }

WORK=${WORKDIR:-$(mktemp -d /tmp/mocap-base.XXXXXX)}
ROOTFS=$WORK/rootfs

# debootstrap mounts /proc and /sys inside the target; a failed run can leave them mounted,
# so unmount whatever is under the root file system before deleting it
cleanup() {
    local m
    for m in $(awk -v r="$ROOTFS/" 'index($2, r) == 1 {print $2}' /proc/mounts | sort -r); do
        umount -l "$m" 2>/dev/null || true
    done
    if [ -n "${WORKDIR:-}" ]; then rm -rf --one-file-system "$ROOTFS"; else rm -rf --one-file-system "$WORK"; fi
}
trap cleanup EXIT

include=$(echo "$BASE_PACKAGES" | xargs | tr ' ' ',')
say "debootstrap --variant=minbase $SUITE from $MIRROR${include:+ with $include}"
start=$SECONDS
debootstrap --variant=minbase ${include:+--include="$include"} "$SUITE" "$ROOTFS" "$MIRROR" \
    >"$WORK/debootstrap.log" 2>&1 || { tail -n 30 "$WORK/debootstrap.log" >&2; say "debootstrap failed"; exit 1; }
rm -rf "$ROOTFS"/var/cache/apt/archives/*.deb "$ROOTFS"/var/lib/apt/lists/* "$ROOTFS"/tmp/*
say "root file system in $((SECONDS - start)) s; importing as $TAG"
tar --numeric-owner -C "$ROOTFS" -c . | $DOCKER import \
    --change 'ENV PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin' \
    --change 'ENV LANG=C.UTF-8' \
    --change 'CMD ["/bin/bash"]' \
    --message "debootstrap --variant=minbase $SUITE $MIRROR" - "$TAG" >/dev/null
say "$TAG ready in $((SECONDS - start)) s"

#!/bin/bash
# Prints the base image docker/Dockerfile should start FROM, making it first
# when needed.
#
#   HITOPS_BASE_IMAGE=debian:bookworm-slim scripts/image-base.sh   # let the tool pull it
#   scripts/image-base.sh                                           # default, see below
#
# Default: when mmdebstrap is installed, a Debian bookworm root filesystem made
# locally (mmdebstrap --variant=minbase, from the Debian mirror apt uses) and
# imported as localhost/hitops-base:bookworm, so no container registry is
# contacted (machines that reach Debian's mirror but not Docker Hub).  Without
# mmdebstrap, debian:bookworm-slim, which the tool pulls.
set -euo pipefail
. "$(dirname "$0")/container-lib.sh"

if [ -n "${HITOPS_BASE_IMAGE:-}" ]; then
    echo "$HITOPS_BASE_IMAGE"
    exit 0
fi
if ! command -v mmdebstrap >/dev/null; then
    note "mmdebstrap not installed: the build pulls debian:bookworm-slim from its registry"
    echo debian:bookworm-slim
    exit 0
fi
TOOL=$(pick_tool) || exit 1
if image_exists "$TOOL" "$LOCAL_BASE"; then
    echo "$LOCAL_BASE"
    exit 0
fi

mkdir -p "$CACHE"
tar=$CACHE/bookworm-minbase.tar
# a directory of that name is what this script made before it said --format=tar
if [ ! -f "$tar" ] || [ ! -s "$tar" ]; then
    rm -rf "$tar" "$tar.part"
    note "mmdebstrap bookworm -> $tar"
    # ca-certificates: apt in the build fetches over https mirrors too.
    # --format=tar: mmdebstrap picks the format from TARGET's extension, and
    # ".part" is none it knows, so without it it writes a directory (which also
    # needs root to come out right)
    mmdebstrap --quiet --variant=minbase --format=tar --include=ca-certificates bookworm "$tar.part" \
        || die "mmdebstrap bookworm failed (see above); check that the Debian mirror is reachable"
    mv "$tar.part" "$tar"
fi
note "importing $tar as $LOCAL_BASE ($TOOL)"
case "$TOOL" in
    buildah)
        ctr=$(buildah from scratch)
        # ADD of a local tar unpacks it; a rootfs has no image config, so set PATH
        buildah add "$ctr" "$tar" / >/dev/null
        buildah config --env PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin \
            --cmd /bin/bash "$ctr"
        buildah commit --rm --quiet "$ctr" "$LOCAL_BASE" >/dev/null;;
    podman)
        podman import --quiet --change 'CMD ["/bin/bash"]' "$tar" "$LOCAL_BASE" >/dev/null;;
    docker)
        docker import --change 'CMD ["/bin/bash"]' "$tar" "$LOCAL_BASE" >/dev/null;;
esac
image_exists "$TOOL" "$LOCAL_BASE" || die "importing $tar into $TOOL did not give $LOCAL_BASE"
echo "$LOCAL_BASE"

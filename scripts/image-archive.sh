#!/bin/bash
# `make image-archive`: writes the built image as a docker-archive tarball,
#   $CACHE/hitops-<version>.docker.tar
# the one file to carry to a cluster without registry access (docker load,
# podman load, or apptainer build from it).
# `make image-sif` (--sif): then builds $CACHE/hitops-<version>.sif from that
# archive with Apptainer (or SingularityCE) and docker/hitops.def, which adds
# only a %test and labels to the same image.
set -euo pipefail
. "$(dirname "$0")/container-lib.sh"

IMAGE=$(image_name) || exit 1
version=${IMAGE##*:}
tar=$CACHE/hitops-$version.docker.tar
sif=$CACHE/hitops-$version.sif

if [ "${1:-}" = "--sif" ]; then
    [ -s "$tar" ] || die "no $tar: run \`make image-archive\` first"
    builder=$(command -v apptainer || command -v singularity || true)
    [ -n "$builder" ] || die "neither apptainer nor singularity is installed: copy $tar to a machine that has one and run: apptainer build --build-arg archive=$(basename "$tar") hitops.sif docker/hitops.def"
    note "$(basename "$builder") build $sif from $tar"
    "$builder" build --force --build-arg "archive=$tar" "$sif" "$ROOT/docker/hitops.def" \
        || die "$(basename "$builder") build failed (see above)"
    note "wrote $sif ($(du -h "$sif" | cut -f1)); for Stimela: cp $sif ~/.singularity/$(echo "$IMAGE" | tr / -).simg (the name Stimela looks for)"
    exit 0
fi

# after --sif, which needs apptainer and the tarball, not a container builder
TOOL=$(pick_tool) || exit 1
image_exists "$TOOL" "$IMAGE" || die "$IMAGE is not in $TOOL's storage: run \`make image\` first"
mkdir -p "$CACHE"
rm -f "$tar"
note "$IMAGE -> $tar ($TOOL)"
case "$TOOL" in
    buildah) buildah push --quiet "$IMAGE" "docker-archive:$tar:$IMAGE" >/dev/null;;
    podman) podman save --quiet --format docker-archive -o "$tar" "$IMAGE";;
    docker) docker save -o "$tar" "$IMAGE";;
esac || die "writing $tar failed (see above; it needs about the image's size free in $CACHE)"
note "wrote $tar ($(du -h "$tar" | cut -f1))"

#!/bin/bash
# `make image`: builds docker/Dockerfile into the image cabs/images.yml names,
# offline, with buildah, podman or docker (the first that works; buildah and
# mmdebstrap installed from Debian when none does; see container-lib.sh).
#
#   1. wheelhouse  scripts/image-wheelhouse.sh (host: pip wheel at the host's versions)
#   2. base        scripts/image-base.sh (mmdebstrap rootfs, or debian:bookworm-slim)
#   3. context     $CACHE/context: wheelhouse (hard links), cabs/, recipes/ only, so
#                  docker does not send .venv and out/ (GBs) to its daemon
#   4. build       <tool> build -f docker/Dockerfile -t IMAGE context
#
# Set HITOPS_SKIP_WHEELHOUSE=1 to reuse the wheelhouse as it is (offline rebuild).
set -euo pipefail
. "$(dirname "$0")/container-lib.sh"

TOOL=$(pick_tool) || exit 1
export _HITOPS_BUILDER=$TOOL   # image-base.sh uses it as it is
IMAGE=$(image_name) || exit 1
note "building $IMAGE with $TOOL (cache $CACHE)"
start=$SECONDS

if [ -z "${HITOPS_SKIP_WHEELHOUSE:-}" ]; then
    "$ROOT/scripts/image-wheelhouse.sh"
fi
ls "$CACHE"/wheelhouse/hitops-*.whl >/dev/null 2>&1 \
    || die "no hitops wheel in $CACHE/wheelhouse: run scripts/image-wheelhouse.sh (or unset HITOPS_SKIP_WHEELHOUSE)"
BASE=$("$ROOT/scripts/image-base.sh") || exit 1

ctx=$CACHE/context
rm -rf "$ctx"
mkdir -p "$ctx"
# hard links when the cache shares the filesystem with itself (always), copies otherwise
cp -al "$CACHE/wheelhouse" "$ctx/wheelhouse" 2>/dev/null || cp -a "$CACHE/wheelhouse" "$ctx/wheelhouse"
cp -a "$ROOT/cabs" "$ROOT/recipes" "$ctx/"
find "$ctx" -name __pycache__ -prune -exec rm -rf {} +

# shellcheck disable=SC2046  # the isolation flags are two words on purpose
"$TOOL" build $(build_isolation "$TOOL") --build-arg "BASE=$BASE" \
    -f "$ROOT/docker/Dockerfile" -t "$IMAGE" "$ctx" \
    || die "$TOOL build failed (see above)"
image_exists "$TOOL" "$IMAGE" || die "$TOOL build finished but $IMAGE is not in its storage"

size=$(image_size "$TOOL" "$IMAGE")
note "built $IMAGE in $((SECONDS - start)) s; size ${size:-unknown} ($TOOL)"

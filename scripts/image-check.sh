#!/bin/bash
# `make image-check`: runs the demo recipe natively inside the built image
# (`stimela run /opt/hitops/recipes/fpt-demo.yml` with the image's own Python,
# CASA and WSClean) and natively on the host, then checks that the two
# peak-flux tables hold the same numbers.
#
#   $CACHE/check/native/   host run   (stimela run recipes/fpt-demo.yml)
#   $CACHE/check/image/    image run  (bind-mounted at /check in the container)
#
# HITOPS_NATIVE_DEMO=DIR   reuse a finished host run (a dir= holding peak-flux.json)
#                          instead of running the demo on the host again.
# Both runs start from empty directories, so no step is skipped as fresh.
set -euo pipefail
. "$(dirname "$0")/container-lib.sh"

TOOL=$(pick_tool) || exit 1
IMAGE=$(image_name) || exit 1
image_exists "$TOOL" "$IMAGE" || die "$IMAGE is not in $TOOL's storage: run \`make image\` first"
check=$CACHE/check
mkdir -p "$check"

# ---- the host's run (the reference)
if [ -n "${HITOPS_NATIVE_DEMO:-}" ]; then
    native=$HITOPS_NATIVE_DEMO
    [ -s "$native/peak-flux.json" ] || die "HITOPS_NATIVE_DEMO=$native has no peak-flux.json: run the demo there first or unset it"
    note "host run: reusing $native"
else
    [ -x "$(dirname "$HOST_PY")/stimela" ] || die "no $(dirname "$HOST_PY")/stimela: run \`make setup\` first"
    command -v wsclean >/dev/null || die "wsclean is not on PATH: run \`make setup\` (installs it from Debian)"
    native=$check/native
    rm -rf "$native" "$check/native-logs"
    mkdir -p "$check/native-logs"
    note "host run -> $native"
    t0=$SECONDS
    # the cwd holds Stimela's logs (the recipe writes out/logs/ relative to it)
    (cd "$check/native-logs" \
        && PATH="$(dirname "$HOST_PY"):$PATH" \
           NUMBA_CACHE_DIR="${NUMBA_CACHE_DIR:-$check/numba-cache}" \
           stimela run "$ROOT/recipes/fpt-demo.yml" "dir=$native") > "$check/native.log" 2>&1 \
        || die "the demo failed on the host (log: $check/native.log)"
    note "host run: $((SECONDS - t0)) s"
fi

# ---- the same recipe inside the image: the image's cabs, recipes and Python
run=$check/image
rm -rf "$run"
mkdir -p "$run"
cmd=(stimela run /opt/hitops/recipes/fpt-demo.yml dir=/check/demo)
note "image run ($TOOL) -> $run/demo"
t0=$SECONDS
case "$TOOL" in
    buildah)
        ctr=$(buildah from --name "hitops-check-$$" "$IMAGE")
        trap 'buildah rm "$ctr" >/dev/null 2>&1 || true' EXIT
        buildah run --isolation chroot --volume "$run:/check" --workingdir /check "$ctr" -- "${cmd[@]}" \
            > "$check/image.log" 2>&1 || die "the demo failed inside $IMAGE (log: $check/image.log)";;
    podman|docker)
        "$TOOL" run --rm --volume "$run:/check" --workdir /check "$IMAGE" "${cmd[@]}" \
            > "$check/image.log" 2>&1 || die "the demo failed inside $IMAGE (log: $check/image.log)";;
esac
note "image run: $((SECONDS - t0)) s"

# ---- same numbers?
cat "$run/demo/peak-flux.md"
python3 "$ROOT/scripts/container-compare.py" "$native/peak-flux.json" "$run/demo/peak-flux.json" \
    "the image's peak-flux.json" \
    || die "the image's peak-flux table differs from the host's (above); see $check/image.log"

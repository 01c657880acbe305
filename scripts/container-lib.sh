# shellcheck shell=bash
# Shared by scripts/image-*.sh (sourced, not run): repository paths, the build
# cache, the image name from cabs/images.yml and the choice of container tool.
#
# Environment (all optional):
#   HITOPS_BUILD_CACHE     where the wheelhouse, the base rootfs and the check runs
#                          go (default /var/tmp/hitops-build: outside the repository,
#                          several GB)
#   HITOPS_CONTAINER_TOOL  buildah | podman | docker (default: the first that works,
#                          in that order; see pick_tool)
#   HITOPS_PYTHON          the Python whose environment the wheelhouse copies
#                          (default .venv/bin/python, made by `make setup`)

ROOT=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
CACHE=${HITOPS_BUILD_CACHE:-/var/tmp/hitops-build}
HOST_PY=${HITOPS_PYTHON:-$ROOT/.venv/bin/python}
# the base made by scripts/image-base.sh from mmdebstrap (never a registry name,
# so it cannot be mistaken for Debian's own image)
LOCAL_BASE=localhost/hitops-base:bookworm

die() {
    echo "$(basename "$0"): $*" >&2
    exit 1
}

note() {
    echo "[$(basename "$0") $(date +%H:%M:%S)] $*" >&2
}

# "{registry}/{name}:{version}" from cabs/images.yml, the name Stimela resolves
# for every cab, so the built image is the one the singularity backend looks for.
image_name() {
    local f=$ROOT/cabs/images.yml
    [ -f "$f" ] || die "no $f: run from a HITOPS checkout"
    awk '
        /^[[:space:]]*image:/ { inimg = 1; next }
        inimg && /^[[:space:]]*(registry|name|version):/ {
            key = $1; sub(":", "", key)
            val = $0; sub(/^[^:]*:[[:space:]]*/, "", val); gsub(/["'\'' ]/, "", val)
            v[key] = val
        }
        END {
            if (v["registry"] == "" || v["name"] == "" || v["version"] == "") exit 1
            printf "%s/%s:%s\n", v["registry"], v["name"], v["version"]
        }' "$f" || die "cabs/images.yml: no vars.hitops.image {registry, name, version}"
}

# buildah first: it needs no daemon and builds and runs with chroot isolation,
# which works on machines where podman's runtime (crun) cannot set rlimits and
# no Docker daemon runs.  docker counts only when its daemon answers.
pick_tool() {
    local t=${HITOPS_CONTAINER_TOOL:-}
    if [ -n "$t" ]; then
        case "$t" in buildah|podman|docker) ;; *)
            die "HITOPS_CONTAINER_TOOL=$t: use buildah, podman or docker";;
        esac
        command -v "$t" >/dev/null || die "HITOPS_CONTAINER_TOOL=$t but $t is not on PATH; install it or unset the variable"
        echo "$t"; return
    fi
    if command -v buildah >/dev/null; then echo buildah; return; fi
    if command -v podman >/dev/null; then echo podman; return; fi
    if command -v docker >/dev/null; then
        if docker info >/dev/null 2>&1; then echo docker; return; fi
        die "docker is installed but its daemon does not answer (docker info failed): start it, or install buildah (apt-get install buildah)"
    fi
    die "no container tool: install buildah (apt-get install buildah), podman or docker"
}

# isolation flags: chroot for buildah/podman builds and buildah runs (no user
# namespaces or OCI runtime needed); docker has none
build_isolation() {
    case "$1" in buildah|podman) echo "--isolation chroot";; esac
}

image_exists() {  # tool image
    case "$1" in
        buildah) buildah inspect --type image "$2" >/dev/null 2>&1;;
        podman) podman image exists "$2" >/dev/null 2>&1;;
        docker) docker image inspect "$2" >/dev/null 2>&1;;
    esac
}

# size in bytes as the tool reports it (uncompressed layers)
image_size() {  # tool image
    case "$1" in
        buildah) buildah images --format '{{.Size}}' "$2" 2>/dev/null | head -n 1;;
        podman) podman image inspect --format '{{.Size}}' "$2" 2>/dev/null;;
        docker) docker image inspect --format '{{.Size}}' "$2" 2>/dev/null;;
    esac
}

# shellcheck shell=bash
# Shared by scripts/image-*.sh (sourced, not run): repository paths, the build
# cache, the image name from cabs/images.yml and the choice of container tool.
#
# Environment (all optional):
#   HITOPS_BUILD_CACHE     where the wheelhouse, the base rootfs and the check runs
#                          go (default /var/tmp/hitops-build: outside the repository,
#                          several GB)
#   HITOPS_CONTAINER_TOOL  buildah | podman | docker (default: the first that works,
#                          in that order, and buildah installed from Debian when
#                          none does; see pick_tool)
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

# The builders in the order they are tried.  buildah first: it needs no daemon
# and builds and runs with chroot isolation, which works on machines where
# podman's runtime (crun) cannot set rlimits and no Docker daemon runs.
BUILDERS=(buildah podman docker)

# Why a builder cannot be used here (one phrase), or nothing when it can: it must
# be on PATH and its `info` must answer.  docker's needs the daemon; buildah's
# and podman's read their storage configuration, so a broken one shows here
# rather than halfway through a build.
builder_problem() {  # tool
    local err
    command -v "$1" >/dev/null || { echo "not installed"; return; }
    err=$(timeout 60 "$1" info 2>&1 >/dev/null) && return
    # the last non-empty line is the reason (docker prints its client part first)
    err=$(printf '%s\n' "$err" | grep -v '^[[:space:]]*$' | tail -n 1)
    echo "installed, but \`$1 info\` failed${err:+: $err}"
}

# apt-get, directly as root or through sudo, output appended to a log whose tail
# is shown when it fails (as scripts/setup.sh installs WSClean)
apt_get_logged() {  # log as_root... -- apt-get args...
    local log=$1
    shift
    local as_root=()
    while [ "$1" != -- ]; do as_root+=("$1"); shift; done
    shift
    printf '\n== %(%F %T)T: apt-get %s\n' -1 "$*" >>"$log"
    # "env VAR=value": sudo's env_reset drops a variable set in front of sudo itself
    if ! "${as_root[@]}" env DEBIAN_FRONTEND=noninteractive apt-get "$@" >>"$log" 2>&1; then
        echo "---- last lines of $log ----" >&2
        tail -n 25 "$log" >&2
        echo "----" >&2
        die "apt-get $1 failed (full output in $log): fix the cause shown above, or install buildah yourself, then rerun"
    fi
}

# No builder works: buildah (and mmdebstrap, which makes the base image without
# a registry) from Debian.  Ends with one line when it cannot.  A buildah that is
# installed but fails is not reinstalled (apt-get would change nothing).
install_buildah() {  # why the builders were passed over
    local why=$1 as_root=() log=$CACHE/apt-get.log problem
    command -v buildah >/dev/null \
        && die "no working container builder ($why): fix buildah (see 'buildah info'), install podman, or start docker's daemon, then rerun"
    command -v apt-get >/dev/null \
        || die "no working container builder ($why) and no apt-get to install one: install buildah (or podman, or start docker's daemon), then rerun"
    if [ "$(id -u)" -ne 0 ]; then
        command -v sudo >/dev/null \
            || die "no working container builder ($why) and installing buildah needs root: run 'apt-get install buildah mmdebstrap' as root (or install sudo), then rerun"
        as_root=(sudo)
    fi
    mkdir -p "$CACHE"
    note "no working container builder ($why): installing buildah and mmdebstrap from Debian (${as_root[*]:+sudo }apt-get install buildah mmdebstrap; output in $log)"
    apt_get_logged "$log" "${as_root[@]}" -- update -q
    apt_get_logged "$log" "${as_root[@]}" -- install -y -q buildah mmdebstrap
    problem=$(builder_problem buildah)
    [ -z "$problem" ] || die "after apt-get install buildah, buildah still does not work (buildah $problem): see $log"
}

# Prints the builder to use, and one line on stderr saying which and why the
# others were passed over.  HITOPS_CONTAINER_TOOL names one (checked, never
# installed).  Otherwise the first of BUILDERS that works; when none does,
# buildah is installed.  The scripts export _HITOPS_BUILDER once chosen, so the
# scripts they run (image-base.sh) neither probe nor say it again.
pick_tool() {
    local t=${HITOPS_CONTAINER_TOOL:-} problem tool chosen="" how="" passed=()
    if [ -n "${_HITOPS_BUILDER:-}" ]; then echo "$_HITOPS_BUILDER"; return; fi
    if [ -n "$t" ]; then
        case "$t" in buildah|podman|docker) ;; *)
            die "HITOPS_CONTAINER_TOOL=$t: use buildah, podman or docker";;
        esac
        command -v "$t" >/dev/null || die "HITOPS_CONTAINER_TOOL=$t but $t is not on PATH; install it or unset the variable"
        problem=$(builder_problem "$t")
        [ -z "$problem" ] || die "HITOPS_CONTAINER_TOOL=$t but $t is $problem: fix it or unset the variable"
        note "container builder: $t (HITOPS_CONTAINER_TOOL)"
        echo "$t"; return
    fi
    for tool in "${BUILDERS[@]}"; do
        if [ -n "$chosen" ]; then  # not probed: an earlier one works
            if command -v "$tool" >/dev/null; then passed+=("$tool comes after $chosen")
            else passed+=("$tool not installed"); fi
            continue
        fi
        problem=$(builder_problem "$tool")
        if [ -z "$problem" ]; then chosen=$tool; else passed+=("$tool $problem"); fi
    done
    if [ -z "$chosen" ]; then
        install_buildah "$(join_by '; ' "${passed[@]}")"
        # buildah's entry ("not installed": a broken one is not reinstalled) no longer holds
        chosen=buildah how="installed now from Debian; " passed=("${passed[@]:1}")
    fi
    note "container builder: $chosen (${how}passed over: $(join_by '; ' "${passed[@]}"))"
    echo "$chosen"
}

join_by() {  # separator words...
    local sep=$1 out="" w
    shift
    for w in "$@"; do out+=${out:+$sep}$w; done
    echo "$out"
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

#!/bin/bash
# Fills $HITOPS_BUILD_CACHE/wheelhouse with a wheel of hitops (this checkout,
# with the `hpc` extra) and of every dependency, at the versions installed in
# the host environment (.venv), so that
#   * the image build installs offline (pip inside a container build often
#     cannot reach the package index; air-gapped cluster build nodes never can),
#   * the image runs the same versions as the host, and the demo gives the same
#     numbers in both (`make image-check`).
# Needs the package index from the host (or a pip configuration pointing at a
# mirror); wheels already in the wheelhouse are reused.
set -euo pipefail
. "$(dirname "$0")/container-lib.sh"

[ -x "$HOST_PY" ] || die "no $HOST_PY: run \`make setup\` first (or set HITOPS_PYTHON)"
wh=$CACHE/wheelhouse
mkdir -p "$wh"
# the hitops wheel is rebuilt from this checkout every time (its version does
# not change between commits, so an old one would otherwise be installed)
rm -f "$wh"/hitops-*.whl

# pin every dependency to the host's version; editable installs (hitops itself)
# and direct-URL installs cannot be constraints
constraints=$CACHE/constraints.txt
"$HOST_PY" -m pip freeze --exclude-editable | grep -v -e '^hitops[=@ ]' -e ' @ ' -e '^-e ' \
    > "$constraints" || die "pip freeze failed in $HOST_PY"

note "pip wheel $ROOT[hpc] -> $wh ($(wc -l < "$constraints") pins from $HOST_PY)"
# --find-links: wheels fetched before are reused, so a rebuild needs the index
# only for what changed; pip builds any sdist-only dependency here, on the host,
# so the image needs no compiler
"$HOST_PY" -m pip wheel --quiet --wheel-dir "$wh" --find-links "$wh" \
    --constraint "$constraints" "$ROOT[hpc]" \
    || die "pip wheel failed (see above): the host must reach the package index (or a mirror) to fill $wh"
ls "$wh"/hitops-*.whl >/dev/null 2>&1 || die "pip wheel made no hitops wheel in $wh"
note "wheelhouse: $(ls "$wh" | wc -l) wheels, $(du -sh "$wh" | cut -f1)"

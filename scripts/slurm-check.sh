#!/bin/bash
# `make slurm-check`: on a one-node slurm cluster (scripts/slurm-local.sh, torn
# down afterwards)
#   1. `stimela run --slurm recipes/fpt-demo.yml`: every step through srun; its
#      peak-flux table must equal the native run's;
#   2. `hitops calibrate --scheduler slurm:2`: dask workers as slurm jobs through
#      dask-jobqueue; PWC_DATA, CFPT_DATA and FLAG must equal the threaded run's.
# The slurm job list (jobcomp) is printed: the step and dask-worker jobs by name.
#
#   scripts/slurm-check.sh            # brings up the local cluster
#   scripts/slurm-check.sh --inside   # on a machine where sbatch/srun already work
#
# The native reference is $CACHE/check/native (from `make image-check`) when it
# exists, else it is run here.  Outputs in $CACHE/slurm/.
set -euo pipefail
. "$(dirname "$0")/container-lib.sh"

if [ "${1:-}" != "--inside" ]; then
    exec "$ROOT/scripts/slurm-local.sh" run -- "$0" --inside
fi

BIN=$(dirname "$HOST_PY")
[ -x "$BIN/stimela" ] || die "no $BIN/stimela: run \`make setup\` first"
command -v srun >/dev/null || die "srun not found: apt-get install slurm-wlm, or run on a slurm login node"
export PATH="$BIN:$PATH"
export NUMBA_CACHE_DIR=${NUMBA_CACHE_DIR:-$CACHE/numba-cache}
out=$CACHE/slurm
rm -rf "$out"
mkdir -p "$out/logs"

# dask-jobqueue: from the project's `hpc` extra; when the environment lacks it,
# a private copy in the cache (the shared .venv is left as `make setup` made it)
if ! "$HOST_PY" -c "import dask_jobqueue" 2>/dev/null; then
    site=$CACHE/hpc-site
    if ! PYTHONPATH=$site "$HOST_PY" -c "import dask_jobqueue" 2>/dev/null; then
        note "dask-jobqueue -> $site"
        "$HOST_PY" -m pip install --quiet --no-deps --target "$site" \
            --find-links "$CACHE/wheelhouse" dask-jobqueue \
            || die "cannot install dask-jobqueue (pip install 'hitops[hpc]' in the environment)"
    fi
    export PYTHONPATH=$site${PYTHONPATH:+:$PYTHONPATH}
fi

# ---- the native reference
native=$CACHE/check/native
if [ ! -s "$native/peak-flux.json" ]; then
    native=$out/native
    note "native run -> $native"
    t0=$SECONDS
    (cd "$out/logs" && stimela run "$ROOT/recipes/fpt-demo.yml" "dir=$native") \
        > "$out/native.log" 2>&1 || die "the native demo failed (log: $out/native.log)"
    note "native run: $((SECONDS - t0)) s"
fi

# ---- 1. the demo, each step through srun
note "stimela run --slurm -> $out/demo"
t0=$SECONDS
(cd "$out/logs" && stimela run --slurm \
    -c opts.backend.slurm.srun_opts.cpus-per-task=2 \
    "$ROOT/recipes/fpt-demo.yml" "dir=$out/demo") > "$out/slurm-demo.log" 2>&1 \
    || die "stimela run --slurm failed (log: $out/slurm-demo.log)"
note "stimela run --slurm: $((SECONDS - t0)) s"
python3 "$ROOT/scripts/container-compare.py" "$native/peak-flux.json" "$out/demo/peak-flux.json" \
    "the srun run's peak-flux.json" || die "the srun run's peak-flux table differs from the native one"

# ---- 2. hitops calibrate: threads vs dask workers started by dask-jobqueue
for mode in threads slurm; do
    mkdir -p "$out/cal-$mode"
    cp -a "$native/sim-86.ms" "$native/sim-230.ms" "$out/cal-$mode/"
done
cal=(calibrate --method pwc,cfpt --offset-reference-column CORRECTED_DATA --max-offset-wraps 50
     --overwrite)
t0=$SECONDS
hitops "${cal[@]}" "$out/cal-threads/sim-86.ms" "$out/cal-threads/sim-230.ms" \
    > "$out/cal-threads.log" 2>&1 || die "hitops calibrate (threads) failed (log: $out/cal-threads.log)"
note "hitops calibrate, threads: $((SECONDS - t0)) s"
t0=$SECONDS
# the worker jobs' slurm-*.out land in the cwd
(cd "$out/cal-slurm" && hitops "${cal[@]}" --scheduler slurm:2 sim-86.ms sim-230.ms) \
    > "$out/cal-slurm.log" 2>&1 || die "hitops calibrate --scheduler slurm:2 failed (log: $out/cal-slurm.log)"
note "hitops calibrate --scheduler slurm:2: $((SECONDS - t0)) s"
grep -E "slurm:|scheduler slurm" "$out/cal-slurm.log" | sed 's/^/    /' >&2 || true
"$HOST_PY" "$ROOT/scripts/container-compare-ms.py" "$out/cal-threads/sim-230.ms" \
    "$out/cal-slurm/sim-230.ms" PWC_DATA CFPT_DATA FLAG \
    || die "--scheduler slurm:2 output differs from the threaded run's"

# ---- what ran through slurm
jobs=$(dirname "${SLURM_CONF:-/nonexistent}")/jobcomp.log
if [ -s "$jobs" ]; then
    note "slurm jobs (jobcomp):"
    sed -E 's/.*JobId=([0-9]+).*Name=([^ ]+).*JobState=([A-Z]+).*StartTime=([^ ]+) EndTime=([^ ]+).*/    job \1 \2 \3 \4 -> \5/' "$jobs" >&2
    cp "$jobs" "$out/jobcomp.log"
fi
note "slurm-check passed (outputs in $out)"

#!/bin/bash
# A throw-away one-node slurm cluster on this machine (Debian's slurm-wlm and
# munge), everything in a temporary directory: munge key and socket, slurm.conf,
# state, spool, logs.  Nothing under /etc, /run or /var is touched.
#
#   scripts/slurm-local.sh run -- CMD [ARGS...]   # up, run CMD with SLURM_CONF set, down
#   scripts/slurm-local.sh up                     # prints the directory; then
#   export SLURM_CONF=DIR/slurm.conf              #   sbatch, srun, squeue ... work
#   scripts/slurm-local.sh down DIR               # stops the daemons, removes DIR
#
# Needs root (slurmd runs jobs as their submitter) and the packages slurm-wlm
# and munge (apt-get install slurm-wlm munge).  The node offers this machine's
# cores and 90% of its memory in one partition, "local"; no cgroups (process
# tracking by /proc), no accounting database; finished jobs are listed in
# DIR/jobcomp.log.  HITOPS_SLURM_KEEP=1 keeps DIR after
# `run` for its logs (slurmctld.log, slurmd.log, munged.log).
set -euo pipefail

die() { echo "slurm-local.sh: $*" >&2; exit 1; }
note() { echo "[slurm-local.sh $(date +%H:%M:%S)] $*" >&2; }

free_port() {
    python3 -c 'import socket; s = socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])'
}

# kill one daemon by the pid it recorded (never by name: other clusters may run)
stop_pidfile() {
    local f=$1 pid
    [ -s "$f" ] || return 0
    pid=$(cat "$f")
    kill "$pid" 2>/dev/null || return 0
    for _ in $(seq 50); do kill -0 "$pid" 2>/dev/null || return 0; sleep 0.1; done
    kill -9 "$pid" 2>/dev/null || true
}

down() {
    local dir=$1
    [ -f "$dir/slurm.conf" ] || die "$dir is not a slurm-local.sh directory (no slurm.conf)"
    # jobs first (their processes are the daemons' children), then the daemons
    if [ -s "$dir/slurmctld.pid" ] && kill -0 "$(cat "$dir/slurmctld.pid")" 2>/dev/null; then
        SLURM_CONF=$dir/slurm.conf scancel --quiet --user="$(id -un)" 2>/dev/null || true
    fi
    stop_pidfile "$dir/slurmd.pid"
    stop_pidfile "$dir/slurmctld.pid"
    stop_pidfile "$dir/munged.pid"
}

up() {
    local missing=()
    for c in munged slurmctld slurmd srun sbatch squeue scancel sinfo; do
        command -v "$c" >/dev/null || missing+=("$c")
    done
    [ ${#missing[@]} -eq 0 ] || die "${missing[*]} not found: apt-get install slurm-wlm munge"
    [ "$(id -u)" -eq 0 ] || die "needs root (slurmd starts jobs as their users); run as root or use a real cluster"

    local dir host cpus mem_mb
    dir=$(mktemp -d "${TMPDIR:-/tmp}/hitops-slurm.XXXXXX")
    chmod 700 "$dir"
    mkdir -p "$dir/state" "$dir/spool" "$dir/munge"
    chmod 700 "$dir/munge"
    host=$(hostname -s)
    cpus=$(nproc)
    mem_mb=$(awk '/MemTotal/ { printf "%d", $2 / 1024 * 0.9 }' /proc/meminfo)

    # munge: its own key and socket, so the machine's munge (if any) is untouched
    dd if=/dev/urandom of="$dir/munge/munge.key" bs=1024 count=1 status=none
    chmod 400 "$dir/munge/munge.key"
    munged --force --key-file="$dir/munge/munge.key" --socket="$dir/munge/munge.socket" \
        --pid-file="$dir/munged.pid" --log-file="$dir/munged.log" \
        --seed-file="$dir/munge/munged.seed" \
        || die "munged did not start (log: $dir/munged.log)"

    cat > "$dir/slurm.conf" <<EOF
# written by scripts/slurm-local.sh: a one-node cluster in $dir
ClusterName=hitopslocal
SlurmctldHost=$host(127.0.0.1)
SlurmUser=root
SlurmdUser=root
SlurmctldPort=$(free_port)
SlurmdPort=$(free_port)
AuthType=auth/munge
AuthInfo=socket=$dir/munge/munge.socket
CredType=cred/munge
StateSaveLocation=$dir/state
SlurmdSpoolDir=$dir/spool
SlurmctldPidFile=$dir/slurmctld.pid
SlurmdPidFile=$dir/slurmd.pid
SlurmctldLogFile=$dir/slurmctld.log
SlurmdLogFile=$dir/slurmd.log
SlurmdDebug=info
SlurmctldDebug=info
# no cgroups: processes tracked through /proc, no task binding or accounting
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
JobAcctGatherType=jobacct_gather/none
AccountingStorageType=accounting_storage/none
# one line per finished job (name, state, times): shows what ran through slurm
JobCompType=jobcomp/filetxt
JobCompLoc=$dir/jobcomp.log
MpiDefault=none
MailProg=/bin/true
SwitchType=switch/none
SelectType=select/cons_tres
SelectTypeParameters=CR_Core
ReturnToService=2
SchedulerType=sched/backfill
NodeName=$host NodeAddr=127.0.0.1 CPUs=$cpus RealMemory=$mem_mb State=UNKNOWN
PartitionName=local Nodes=$host Default=YES MaxTime=INFINITE State=UP
EOF
    export SLURM_CONF=$dir/slurm.conf
    slurmctld -i || die "slurmctld did not start (log: $dir/slurmctld.log)"
    slurmd || die "slurmd did not start (log: $dir/slurmd.log)"
    # the node must register and become idle before jobs can run on it
    local state=""
    for _ in $(seq 60); do
        state=$(sinfo --noheader --nodes="$host" --format=%T 2>/dev/null || true)
        [ "$state" = idle ] && break
        sleep 0.5
    done
    if [ "$state" != idle ]; then
        echo "--- slurmctld.log"; tail -n 15 "$dir/slurmctld.log" 2>/dev/null
        echo "--- slurmd.log"; tail -n 15 "$dir/slurmd.log" 2>/dev/null
        down "$dir"
        die "node $host did not become idle (state '${state:-none}'; logs above, kept in $dir)"
    fi >&2
    note "one-node cluster up: $host, $cpus CPUs, $mem_mb MB, SLURM_CONF=$dir/slurm.conf"
    echo "$dir"
}

case "${1:-}" in
    up)
        up;;
    down)
        [ -n "${2:-}" ] || die "usage: slurm-local.sh down DIR"
        down "$2"
        rm -rf "$2";;
    run)
        shift
        [ "${1:-}" = "--" ] && shift
        [ $# -gt 0 ] || die "usage: slurm-local.sh run -- CMD [ARGS...]"
        dir=$(up) || exit 1
        # shellcheck disable=SC2064  # expand $dir now
        trap "down '$dir'; if [ -z '${HITOPS_SLURM_KEEP:-}' ]; then rm -rf '$dir'; else echo 'slurm-local.sh: kept $dir' >&2; fi" EXIT
        SLURM_CONF=$dir/slurm.conf "$@";;
    *)
        die "usage: slurm-local.sh up | down DIR | run -- CMD [ARGS...]";;
esac

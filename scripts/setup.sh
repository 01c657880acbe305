#!/usr/bin/env bash
# HITOPS set-up, one step per argument (no argument: every step, in order):
#
#   venv         .venv with the Python packages (pip install -e '.[test,ehtim,msv4]'), redone
#                only when pyproject.toml is newer than .venv/.hitops-installed
#   wsclean      WSClean from Debian when it is not on PATH (apt-get; through sudo
#                when not root)
#   browser      Chromium and chromedriver from Debian when missing (the run page's
#                browser tests), the same way
#   casa-config  CASA's offline data configuration, inside the environment
#                (.venv/etc/hitops/casasiteconfig.py; hitops/casa_env.py)
#   numba-cache  the directory numba caches its compiled kernels in
#
# The Makefile calls these steps (make setup/run/test); tests/test_setup.py runs
# them with stand-ins for apt-get, sudo and id. Each step prints one line; the
# output of pip and apt-get goes to $VENV/setup.log, whose tail is shown when a
# step fails.
#
# Settings (environment): PYTHON (default python3), VENV (default .venv, relative
# to the repository), NUMBA_CACHE_DIR (default $VENV/numba-cache).
set -euo pipefail

cd "$(dirname "${BASH_SOURCE[0]}")/.."

PYTHON=${PYTHON:-python3}
VENV=${VENV:-.venv}
PY=$VENV/bin/python
STAMP=$VENV/.hitops-installed
LOG=$VENV/setup.log
NUMBA_CACHE_DIR=${NUMBA_CACHE_DIR:-$VENV/numba-cache}

say() { printf 'setup: %s\n' "$*"; }

# every failure ends with exactly one line that names what failed and the remedy
fail() {
    printf 'setup: %s\n' "$*" >&2
    exit 1
}

# Run a command with its output appended to the log; on failure show the log's
# tail (the actual error from pip or apt-get) and one line saying what to do.
run_logged() {
    local what=$1
    shift
    mkdir -p "$VENV"
    printf '\n== %(%F %T)T: %s\n' -1 "$*" >>"$LOG"
    if ! "$@" >>"$LOG" 2>&1; then
        printf '%s\n' "---- last lines of $LOG ----" >&2
        tail -n 25 "$LOG" >&2
        printf '%s\n' "----" >&2
        fail "$what failed (full output in $LOG); fix the cause shown above and rerun 'make setup'"
    fi
}

step_venv() {
    # same rule as make's "$(STAMP): pyproject.toml": redo only when pyproject.toml changed
    if [ -x "$PY" ] && [ -f "$STAMP" ] && ! [ pyproject.toml -nt "$STAMP" ]; then
        say "Python environment $VENV is up to date"
        return
    fi
    command -v "$PYTHON" >/dev/null ||
        fail "$PYTHON not found: install Python 3.10-3.12 (apt-get install python3 python3-venv) or name one with 'make setup PYTHON=python3.12'"
    # pip's own refusal (requires-python) is a page of text; say it in one line first
    "$PYTHON" -c 'import sys; sys.exit(not (3, 10) <= sys.version_info[:2] < (3, 13))' ||
        fail "$PYTHON is Python $("$PYTHON" -c 'import platform; print(platform.python_version())'); HITOPS needs 3.10-3.12: name one with 'make setup PYTHON=python3.12'"
    say "installing the Python packages into $VENV (a few minutes the first time; output in $LOG)"
    run_logged "creating the virtual environment $VENV (Debian needs the python3-venv package)" \
        "$PYTHON" -m venv "$VENV"
    run_logged "upgrading pip in $VENV" "$PY" -m pip install --progress-bar off --upgrade pip
    # ehtim: the eht-imaging client that reads our UVFITS in the tests (tests/test_interop_ehtim.py);
    # msv4: xradio/zarr for MSv4 processing sets (hitops/io/msv4/, tests/test_msv4*.py)
    run_logged "pip install -e '.[test,ehtim,msv4]'" "$PY" -m pip install --progress-bar off -e '.[test,ehtim,msv4]'
    touch "$STAMP"
}

# Debian packages that provide commands, installed only when a command is missing:
# from_debian WHAT "COMMAND ..." "PACKAGE ..."
from_debian() {
    local what=$1 commands=$2 packages=$3 cmd missing=""
    for cmd in $commands; do
        command -v "$cmd" >/dev/null || missing="$missing $cmd"
    done
    if [ -z "$missing" ]; then
        local found=()
        for cmd in $commands; do found+=("$(command -v "$cmd")"); done
        say "$what found: ${found[*]}"
        return
    fi
    command -v apt-get >/dev/null ||
        fail "$what is not on PATH and there is no apt-get to install it: install $what yourself, then rerun 'make setup'"
    local as_root=()
    if [ "$(id -u)" -ne 0 ]; then
        command -v sudo >/dev/null ||
            fail "$what is not on PATH and installing it needs root: run 'apt-get install $packages' as root (or install sudo), then rerun 'make setup'"
        as_root=(sudo)
    fi
    # "env VAR=value apt-get" rather than "VAR=value apt-get": with as_root empty
    # the assignment would be run as a command (issue 11), and sudo's env_reset
    # drops a variable set in front of sudo itself
    say "installing $what from Debian (${as_root[*]:+${as_root[*]} }apt-get install $packages; output in $LOG)"
    run_logged "apt-get update" \
        "${as_root[@]}" env DEBIAN_FRONTEND=noninteractive apt-get update -q
    # $packages unquoted: one word per package
    # shellcheck disable=SC2086
    run_logged "apt-get install $packages" \
        "${as_root[@]}" env DEBIAN_FRONTEND=noninteractive apt-get install -y -q $packages
    for cmd in $commands; do
        command -v "$cmd" >/dev/null ||
            fail "apt-get installed $packages but no $cmd is on PATH ($PATH): see 'dpkg -L ${packages%% *}'"
    done
}

step_wsclean() {
    from_debian WSClean "wsclean" "wsclean"
}

# the headless browser the run's page is tested in (tests/test_report*.py): Debian's
# Chromium and its WebDriver, nothing that downloads a browser of its own
step_browser() {
    from_debian Chromium "chromium chromedriver" "chromium chromium-driver"
}

step_casa_config() {
    local path
    # python -m hitops.casa_env writes the file (under the environment's sys.prefix)
    # and prints its path; its own errors are one line on stderr (HitopsError)
    path=$("$PY" -m hitops.casa_env) ||
        fail "writing CASA's offline data configuration failed (see the line above); rerun 'make setup' after fixing it"
    say "CASA offline data configuration: $path"
}

step_numba_cache() {
    mkdir -p "$NUMBA_CACHE_DIR"
    say "numba kernel cache: $NUMBA_CACHE_DIR"
}

steps=("$@")
[ ${#steps[@]} -gt 0 ] || steps=(venv wsclean browser casa-config numba-cache)
for step in "${steps[@]}"; do
    case $step in
    venv) step_venv ;;
    wsclean) step_wsclean ;;
    browser) step_browser ;;
    casa-config) step_casa_config ;;
    numba-cache) step_numba_cache ;;
    *) fail "unknown step '$step': use venv, wsclean, browser, casa-config or numba-cache (scripts/setup.sh)" ;;
    esac
done

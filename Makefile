# HITOPS: `make run` and `make test` each set up everything on a fresh machine
# (virtual environment, Python packages, WSClean, CASA's offline data
# configuration) and then run the demo recipe or the tests. The set-up steps
# are in scripts/setup.sh, where tests/test_setup.py runs them; `make help`
# lists the targets (the text after "##" on each target's line).
SHELL := /bin/bash
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.hitops-installed
SETUP := $(SHELL) scripts/setup.sh
# scripts/setup.sh reads these (e.g. make setup PYTHON=python3.12)
export PYTHON VENV
# the venv's console scripts (hitops, stimela) must be found by Stimela's native backend
export PATH := $(abspath $(VENV))/bin:$(PATH)
# numba's compiled kernels are cached here between runs
export NUMBA_CACHE_DIR ?= $(abspath $(VENV))/numba-cache

.PHONY: help setup run test bench cabs wsclean browser casa-config numba-cache clean
# `make` alone sets up, as before `make help` existed
.DEFAULT_GOAL := setup

help: ## list the targets
	@awk -F ':.*## ' '/^[a-zA-Z_.-]+:.*## /{printf "make %-12s %s\n", $$1, $$2}' $(MAKEFILE_LIST)

setup: $(STAMP) wsclean browser casa-config numba-cache ## set up: .venv with the Python packages, WSClean, Chromium, CASA offline data, numba cache

$(STAMP): pyproject.toml
	@$(SETUP) venv

wsclean: ## install WSClean from Debian when missing (apt-get; through sudo when not root)
	@$(SETUP) wsclean

browser: ## install Chromium and chromedriver from Debian when missing (the run page's browser tests)
	@$(SETUP) browser

casa-config: $(STAMP) ## write CASA's offline data configuration into .venv/etc/hitops/
	@$(SETUP) casa-config

numba-cache: ## create the numba kernel cache directory (.venv/numba-cache)
	@$(SETUP) numba-cache

# ARGS: recipe parameters and runner options, e.g. make run ARGS='seed=11 fringefit_solint=30s' or ARGS=-v
run: setup ## set up, then run the demo recipe quietly: one line per step, then the result table (out/demo/; ARGS='-v seed=11')
	@$(PY) -m hitops.run recipes/fpt-demo.yml $(ARGS)

# test files spread over this many processes (pytest-xdist; 0: one process). A file's
# tests stay together on one worker (--dist loadfile): its module fixtures are built once
TEST_WORKERS ?= 2

test: setup ## set up, then run all the tests, files spread over TEST_WORKERS processes (default 2; 0: one)
	$(PY) -m pytest -q --durations=20 -n $(TEST_WORKERS) --dist loadfile

bench: setup ## set up, then run every benchmark (each rewrites its section of docs/performance.md)
	$(PY) -m benchmarks.run_all

cabs: $(STAMP) ## regenerate cabs/hitops.yml from hitops/schemas/
	$(PY) -m hitops.cabgen

clean: ## remove out/, bench-out/ and .pytest_cache (keeps .venv)
	rm -rf out bench-out .pytest_cache

include mk/containers.mk

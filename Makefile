# HITOPS: `make run` and `make test` each set up everything on a fresh machine
# (virtual environment, Python packages, WSClean, CASA's offline data
# configuration) and then run the demo recipe or the tests.
SHELL := /bin/bash
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.hitops-installed
# the venv's console scripts (hitops, stimela) must be found by Stimela's native backend
export PATH := $(CURDIR)/$(VENV)/bin:$(PATH)
# numba's compiled kernels are cached here between runs
export NUMBA_CACHE_DIR ?= $(CURDIR)/.venv/numba-cache

.PHONY: setup run test bench cabs wsclean casa-config clean

setup: $(STAMP) wsclean casa-config

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[test]'
	touch $@

# WSClean from Debian, installed only when missing (root, or sudo when not root)
wsclean:
	@command -v wsclean >/dev/null || { \
	  SUDO=$$([ "$$(id -u)" -eq 0 ] || echo sudo); \
	  $$SUDO apt-get update -q && $$SUDO DEBIAN_FRONTEND=noninteractive apt-get install -y -q wsclean; }

# CASA offline data configuration in ~/.cache/hitops, never in the user's ~/.casa
casa-config: $(STAMP)
	@$(PY) -m hitops.casa_env >/dev/null

run: setup
	stimela run recipes/fpt-demo.yml

test: setup
	$(PY) -m pytest -q

bench: setup
	$(PY) -m benchmarks.run_all

# regenerate cabs/hitops.yml from the parameter schemas
cabs: $(STAMP)
	$(PY) -m hitops.cabgen

clean:
	rm -rf out bench-out .pytest_cache

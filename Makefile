# gcvd-flow: `make demo` and `make test` set everything up themselves on a fresh machine.
SHELL := /bin/bash
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
SUDO := $(shell [ "$$(id -u)" = 0 ] || echo sudo)
export MPLBACKEND := Agg

.PHONY: setup demo test lint check-install test-fast bench-engine bench-accuracy bench-runtime bench-cost bench-peer bench-scale bench-sweep clean sysdeps peerdeps testdeps regress regress-baseline

setup: $(STAMP)

# open3d-cpu needs Debian's libusb-1.0-0 at import time.
sysdeps:
	@if ! ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0'; then \
	  echo "installing Debian package libusb-1.0-0 (needed by open3d)"; \
	  $(SUDO) apt-get update -qq && DEBIAN_FRONTEND=noninteractive $(SUDO) apt-get install -y -qq libusb-1.0-0 >/dev/null; \
	fi
	@# the SFTP remote-cache test starts its own sshd on a 127.0.0.1 port (tests/remote_servers.py);
	@# note: on a machine with an init system Debian also enables its ssh service when installed
	@if [ ! -x /usr/sbin/sshd ]; then \
	  echo "installing Debian package openssh-server (the SFTP remote-cache test runs sshd on loopback)"; \
	  $(SUDO) apt-get update -qq && DEBIAN_FRONTEND=noninteractive $(SUDO) apt-get install -y -qq openssh-server >/dev/null || \
	  echo "openssh-server not installed: the SFTP test will be skipped"; \
	fi

# The report test renders the page in headless Chromium (Debian's chromium); installed when
# missing. If apt-get cannot install it, the test prints why and is skipped.
testdeps:
	@if ! command -v chromium >/dev/null 2>&1; then \
	  echo "installing Debian package chromium (headless rendering of gcvd-flow report in the tests)"; \
	  ( $(SUDO) apt-get update -qq && $(SUDO) env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium >/dev/null ) \
	    || echo "could not install chromium: tests/test_report.py will skip its rendering tests"; \
	fi

$(STAMP): requirements.txt requirements-test.txt pyproject.toml | sysdeps
	@test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/pip install -q --disable-pip-version-check -r requirements.txt -r requirements-test.txt
	$(BIN)/pip install -q --disable-pip-version-check --no-deps --no-build-isolation -e .
	@touch $(STAMP)

demo: $(STAMP)
	$(BIN)/python -m gcvd_flow demo

test: $(STAMP) testdeps lint
	$(BIN)/python -m pytest -q -n 2 --dist loadfile --durations=15

# ruff (pyflakes, import order, bugbear, numpy rules) and mypy (pyproject.toml [tool.mypy]) on the whole package
lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/python -m mypy

# a fresh venv (no system site-packages), torch as requirements.txt pins it, `pip install .`, then
# synth + run + report + export from outside the checkout: catches an undeclared dependency
check-install: sysdeps
	PY=$(PY) .ci/check-install

test-fast: $(STAMP)
	$(BIN)/python -m pytest -q -x -m "not slow"

bench-engine: $(STAMP)
	$(BIN)/pip install -q --disable-pip-version-check -r benchmarks/requirements-bench.txt
	$(BIN)/python benchmarks/bench_engine.py

bench-accuracy: $(STAMP)
	$(BIN)/python benchmarks/bench_accuracy.py

bench-runtime: $(STAMP)
	$(BIN)/python benchmarks/bench_runtime.py
	$(BIN)/python benchmarks/bench_runtime.py --real
	$(BIN)/python benchmarks/bench_runtime.py --side-by-side 30 --size 128x96
	$(BIN)/python benchmarks/bench_runtime.py --side-by-side 100 --trajectory scan --size 256x192 --policies passive

# wall time against a reference commit, alternating on ICL, the HoloLens walk and KITTI (issue 38):
# per-stage seconds, cores busy, peak memory, ratio. The references are detached worktrees next to
# this checkout (made here when absent); e.g. make bench-cost COST_ARGS="--clips icl --repeat 2"
COST_REF ?= 5261f0f
COST_ALSO ?= aaaa9c0
bench-cost: $(STAMP)
	@for c in $(COST_REF) $(COST_ALSO); do test -d ../ref-$$c || git worktree add --detach ../ref-$$c $$c; done
	$(BIN)/python benchmarks/bench_cost.py --ref ../ref-$(COST_REF) $(foreach c,$(COST_ALSO),--also ../ref-$(c)) $(COST_ARGS)

# map stages' throughput on 1 vs 2 Dask workers, and a cluster projection (docs/teams.md)
bench-scale: $(STAMP)
	$(BIN)/python benchmarks/bench_scale.py $(SCALE_ARGS)

# a 3-value sweep against one run alone, alternating (docs/benchmarks.md, "Parameter sweeps")
bench-sweep: $(STAMP)
	$(BIN)/python benchmarks/bench_sweep.py $(SWEEP_ARGS)

# The peer of bench-peer: Debian's colmap (3.8, CPU), only when it is not on PATH.
# Not a dependency of setup/test/demo.
peerdeps:
	@if ! command -v colmap >/dev/null 2>&1; then \
	  echo "installing Debian package colmap (the peer of make bench-peer)"; \
	  $(SUDO) apt-get update -qq && $(SUDO) env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq colmap >/dev/null; \
	fi

# gcvd-flow vs COLMAP on the ICL-NUIM frames and on forward driving (KITTI 07, frames 0-99), one
# table each; e.g. make bench-peer PEER_ARGS="--frames 30 --json", or PEER_DATA=... for other folders
PEER_DATA ?= $(ICL) ../shared/data/kitti07_first100
bench-peer: $(STAMP) peerdeps
	@for d in $(PEER_DATA); do \
	  echo "bench-peer: $$d"; \
	  $(BIN)/python benchmarks/bench_peer.py --data $$d $(PEER_ARGS) || exit 1; \
	done

# CI regression check: GCVD on the shared ICL-NUIM frames at a small size (60 frames, 128 px,
# about a minute on 2 cores), metrics compared with benchmarks/regress_baseline.json: exit 1 with
# one line per metric worse by more than REGRESS_TOL. `make regress-baseline` rewrites the
# baseline from the current code (commit it with the change that moved the numbers).
ICL ?= ../shared/data/icl_livingroom1_micro
REGRESS_DIR ?= build/regress
REGRESS_TOL ?= 5%
REGRESS_ARGS := --set ingest.end=60 --set ingest.long_side=128
regress: $(STAMP)
	@test -d $(ICL) || { echo "make regress: needs the ICL frames in $(ICL) (see its README)"; exit 2; }
	$(BIN)/gcvd-flow run $(ICL) --out $(REGRESS_DIR)/run --cache $(REGRESS_DIR)/cache $(REGRESS_ARGS)
	$(BIN)/gcvd-flow eval $(REGRESS_DIR)/run --gt $(ICL) --baseline benchmarks/regress_baseline.json --tolerance $(REGRESS_TOL)

regress-baseline: $(STAMP)
	$(BIN)/gcvd-flow run $(ICL) --out $(REGRESS_DIR)/run --cache $(REGRESS_DIR)/cache $(REGRESS_ARGS)
	$(BIN)/gcvd-flow eval $(REGRESS_DIR)/run --gt $(ICL) --no-write --json > $(REGRESS_DIR)/metrics.json
	$(BIN)/python -c "import json, sys; m = json.load(open('$(REGRESS_DIR)/metrics.json')); \
	  json.dump({'what': 'make regress: gcvd-flow run $(ICL) $(REGRESS_ARGS); gcvd-flow eval --gt $(ICL)', \
	             'metrics': m}, open('benchmarks/regress_baseline.json', 'w'), indent=1, sort_keys=True)"
	@echo "wrote benchmarks/regress_baseline.json"

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache

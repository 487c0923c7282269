# Two entry points: `make demo` (main job on bundled data) and `make test` (the suite).
# Both create or refresh .venv first, so they work on a fresh machine.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
# This machine keeps a CPU wheel of torch in /opt/wheels; use it when present (elsewhere,
# install the torch build you want first: see README, "Installing torch").
WHEELS := $(firstword $(wildcard /opt/wheels))
PIP_INSTALL := $(BIN)/python -m pip install -q $(if $(WHEELS),--find-links $(WHEELS),)

.PHONY: demo test lint bench clean

$(STAMP): pyproject.toml
	$(PY) -m venv $(VENV)
	$(PIP_INSTALL) --upgrade pip
	$(PIP_INSTALL) torch==2.13.0
	$(PIP_INSTALL) -e '.[test,distributed,perception]'
	# the person detector: without its declared dependencies (see pyproject's perception extra)
	$(PIP_INSTALL) --no-deps mediapipe==0.10.14
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/python -m motion demo --out runs/demo

test: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/python -m pytest -n 2 -q

lint: $(STAMP)
	$(BIN)/ruff check .

# every benchmarks/bench_*.py, each in its own process; writes docs/benchmarks.md from their
# figures (`make bench BENCH=--quick`: each one's smaller problem)
bench: $(STAMP)
	$(BIN)/python benchmarks/report.py $(BENCH)

clean:
	rm -rf $(VENV)

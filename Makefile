# Quick start: `make demo` and `make test`. Each target sets up what it needs.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
DEMO_DIR ?= demo
DEMO_CLIP ?= common/data/clips/cmu_12_01_walk.bvh

.PHONY: venv demo test test-all bench cluster cluster-test clean

$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[test]'
	touch $(STAMP)

venv: $(STAMP)

demo: $(STAMP)
	$(PY) -m server.demo --out $(DEMO_DIR) --clip $(DEMO_CLIP)

test: $(STAMP)
	$(PY) -m pytest -q -m "not slow" tests

test-all: $(STAMP)
	$(PY) -m pytest -q tests

bench: $(STAMP)
	$(PY) -m server.cli bench all --out bench

clean:
	rm -rf $(VENV) $(DEMO_DIR) bench/*.json .pytest_cache

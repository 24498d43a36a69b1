# Quick start: `make demo` and `make test`. Each target sets up what it needs.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
DEMO_DIR ?= demo
DEMO_CLIP ?= common/data/clips/cmu_12_01_walk.bvh

.PHONY: venv demo test test-all test-slow real-test batch-test bench reliability interop-test install-test cluster cluster-test batch-cluster-test clean

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

# The slow tests that no other target runs (whole first-frame searches, the video chain, ...).
test-slow: $(STAMP)
	$(PY) -m pytest -q -m slow tests --ignore=tests/test_real_take.py --ignore=tests/test_batch.py \
		--ignore=tests/test_install.py

# The real seated take of ../shared, end to end with the project's commands (skips without it).
real-test: $(STAMP)
	$(PY) -m pytest -q -s tests/test_real_take.py

# mocap run and mocap batch on real local Dask clusters (2 worker processes), a worker killed mid-batch.
batch-test: $(STAMP)
	$(PY) -m pytest -q tests/test_batch.py

# The wheel, installed in a fresh venv outside the repository, runs `mocap demo` on its bundled data.
install-test: $(STAMP)
	$(PY) -m pytest -q tests/test_install.py

bench: $(STAMP)
	$(PY) -m server.cli bench all --out bench

# Our exports opened by Blender (BVH, GLB), OpenSim (TRC, MOT), the Khronos validator and three.js in
# headless Chromium; installs Debian's blender and chromium and npm packages where missing.
interop-test: $(STAMP)
	$(PY) tools/interop_test.py

# Bad inputs, injected faults and a long fuzz run, counted into bench/reliability.json.
reliability: $(STAMP)
	$(PY) tools/reliability.py --out bench/reliability.json

# The fitting cluster as containers (server + 4 clients) on a private Docker engine; needs root.
# cluster: the demo sequence, its summary, single process vs distributed (images kept in
# build/cluster); cluster-test: all of it from nothing, checked, then torn down (deploy/cluster.sh).
cluster: $(STAMP)
	PY=$(abspath $(PY)) deploy/cluster.sh demo

cluster-test: $(STAMP)
	PY=$(abspath $(PY)) deploy/cluster.sh test

# mocap batch on a Dask scheduler + 2 worker containers, from nothing, checked, torn down.
batch-cluster-test: $(STAMP)
	PY=$(abspath $(PY)) deploy/cluster.sh batch-test

clean:
	rm -rf $(VENV) $(DEMO_DIR) bench/*.json .pytest_cache
